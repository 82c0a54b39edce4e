"""The Gaussian-mixture action head of the BC policy: its loss, its mode, and the policy around it."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import distributions as D
from torchrl.objectives import BCLoss

from benchmarks.push.bc_evaluation import bc_env
from benchmarks.push.dagger import labelled_episodes
from benchmarks.push.gmm_head import (
    GMM_KEYS,
    GMM_LOC,
    GMM_LOGITS,
    GMM_SCALE,
    GMMActionLoss,
    GMMConfig,
    GMMPolicy,
    most_likely_mean,
)
from benchmarks.push.outage_evaluation import Condition
from mmf_rl.rl import BCPolicy, train_bc, validation_errors
from mmf_rl.rl.action_chunks import ACTION_CHUNK, PAST_CHUNKS_FILLED
from mmf_rl.rl.demonstrations import DEMONSTRATED_CHUNK, DEMONSTRATED_CHUNK_MASK
from mmf_rl.trainers.trainer import seed_everything
from tests.rl.test_action_chunks import act_ensemble
from tests.rl.test_bc import IMAGE_SIZE, TINY, TINY_ENCODERS, TINY_TRAINING, make_policy


def make_gmm_policy(demonstrations, seed: int = 0, **options) -> GMMPolicy:
    """`make_policy`'s tiny policy with the mixture head."""
    seed_everything(seed)
    return GMMPolicy.for_demonstrations(demonstrations, encoders=TINY_ENCODERS, **TINY, **options)


def fixed_mixture(values: dict[tuple, torch.Tensor]) -> TensorDictModule:
    """An 'actor' that writes the given mixture whatever its input (the batch's ``"obs"``)."""

    def write(obs: torch.Tensor):
        return tuple(values[key] for key in GMM_KEYS)

    return TensorDictModule(write, in_keys=["obs"], out_keys=GMM_KEYS)


def test_the_loss_is_the_mean_negative_log_likelihood_of_torch_distributions_mixture():
    generator = torch.Generator().manual_seed(0)
    loc = torch.rand(3, 2, 4, generator=generator) * 2 - 1  # [B, C, A]
    scale = torch.rand(3, 2, 4, generator=generator) + 0.1
    logits = torch.randn(3, 2, generator=generator)
    action = torch.rand(3, 4, generator=generator) * 2 - 1
    loss = GMMActionLoss(fixed_mixture({GMM_LOC: loc, GMM_SCALE: scale, GMM_LOGITS: logits}))
    batch = TensorDict({"obs": torch.zeros(3, 1), "action": action}, batch_size=[3])
    expected = 0.0
    for b in range(3):  # written out per row: weights, per-dim normal densities, log of the sum
        weights = logits[b].softmax(-1)
        density = sum(
            weights[c] * D.Normal(loc[b, c], scale[b, c]).log_prob(action[b]).sum().exp() for c in range(2)
        )
        expected -= density.log() / 3
    torch.testing.assert_close(loss(batch).get("loss_bc"), expected)


def test_the_chunk_loss_masks_the_steps_past_the_episodes_end():
    generator = torch.Generator().manual_seed(1)
    loc = torch.rand(2, 3, 2, 4, generator=generator) * 2 - 1  # [B, k, C, A]
    scale = torch.rand(2, 3, 2, 4, generator=generator) + 0.1
    logits = torch.randn(2, 3, 2, generator=generator)
    chunk = torch.rand(2, 3, 4, generator=generator) * 2 - 1
    mask = torch.tensor([[True, True, True], [True, False, False]])
    loss = GMMActionLoss(fixed_mixture({GMM_LOC: loc, GMM_SCALE: scale, GMM_LOGITS: logits}), chunked=True)
    batch = TensorDict(
        {"obs": torch.zeros(2, 1), DEMONSTRATED_CHUNK: chunk, DEMONSTRATED_CHUNK_MASK: mask}, batch_size=[2]
    )
    mixture = D.MixtureSameFamily(D.Categorical(logits=logits), D.Independent(D.Normal(loc, scale), 1))
    value = loss(batch).get("loss_bc")
    torch.testing.assert_close(value, -mixture.log_prob(chunk)[mask].mean())
    batch.get(DEMONSTRATED_CHUNK)[~mask] = 100.0  # past the episode's end: never read
    torch.testing.assert_close(loss(batch).get("loss_bc"), value)


def test_the_action_is_the_mean_of_the_most_likely_component():
    loc = torch.tensor([[[0.1, 0.2], [0.7, -0.5], [0.3, 0.3]], [[0.9, 0.9], [-0.2, 0.4], [0.0, 0.0]]])
    logits = torch.tensor([[0.0, 2.0, 1.0], [3.0, -1.0, 2.9]])
    torch.testing.assert_close(most_likely_mean(loc, logits), torch.tensor([[0.7, -0.5], [0.9, 0.9]]))
    # With a chunk dim: each step's own mode.
    chunked = most_likely_mean(loc.unsqueeze(0), logits.unsqueeze(0))
    torch.testing.assert_close(chunked, torch.tensor([[[0.7, -0.5], [0.9, 0.9]]]))


def two_mode_fit(policy: BCPolicy, batch: TensorDict, steps: int = 300) -> torch.Tensor:
    """Fit ``policy`` to ``batch`` (the same input on every row, two actions) with its head's loss;
    returns its action on that input afterwards."""
    loss = GMMActionLoss(policy.mixture()) if isinstance(policy, GMMPolicy) else BCLoss(policy)
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    for _ in range(steps):
        optimizer.zero_grad()
        loss(batch.clone()).get("loss_bc").backward()
        optimizer.step()
    with torch.no_grad():
        return policy.eval()(batch[:1].exclude("action")).get("action")[0]


def test_on_two_modes_the_mixture_acts_on_one_where_the_regression_averages_them(demonstrations):
    """The point of the head: the same input labelled 0 half the time and 0.8 the other half."""
    frame = demonstrations.split_frames["train"][:1].expand(32)
    batch = demonstrations.batch(frame)
    noise = 0.05 * torch.randn(32, 4, generator=torch.Generator().manual_seed(0))  # as a demonstrator's
    batch.set("action", torch.cat([torch.zeros(16, 4), torch.full((16, 4), 0.8)]) + noise)
    regression = two_mode_fit(make_policy(demonstrations, seed=0), batch)
    torch.testing.assert_close(regression, torch.full((4,), 0.4), atol=0.05, rtol=0)
    mixture = two_mode_fit(make_gmm_policy(demonstrations, seed=0), batch)
    distance = torch.minimum(mixture.abs(), (mixture - 0.8).abs())
    assert (distance < 0.1).all() and ((mixture - 0.4).abs() > 0.3).all(), mixture


def test_its_checkpoints_are_the_packages_and_each_head_refuses_the_others(demonstrations, tmp_path):
    """The mixture policy's config reads and writes what the package's did when it had the head
    (``action_head: "gmm"``, ``gmm_components``); each policy class loads its own checkpoints only."""
    mixture = make_gmm_policy(demonstrations, seed=3, gmm_components=2)
    written = mixture.config.to_dict()
    assert written["action_head"] == "gmm" and written["gmm_components"] == 2
    assert GMMConfig.from_dict(written) == mixture.config
    regression = make_policy(demonstrations, seed=3)
    mine, theirs = regression.state_dict(), mixture.state_dict()
    assert mine.keys() == theirs.keys() and regression.mode is None and regression.out_keys == ["action"]
    for name in mine:  # the encoders, drawn before the head from the same seed, are the same
        if name.startswith("module.encoders."):
            assert torch.equal(mine[name], theirs[name]), name
    mixture.save(tmp_path / "mixture")
    saved = regression.save(tmp_path / "regression")
    with pytest.raises(ValueError, match="unknown keys \\['action_head', 'gmm_components'\\]"):
        BCPolicy.from_checkpoint(tmp_path / "mixture")
    with pytest.raises(ValueError, match="the 'mse' head, not a mixture"):
        GMMPolicy.from_checkpoint(tmp_path / "regression")
    old = json.loads((saved / "meta.json").read_text())["bc_config"]
    with pytest.raises(ValueError, match="the 'mse' head, not a mixture"):
        GMMConfig.from_dict({**old, "action_head": "mse", "gmm_components": 5})
    with pytest.raises(ValueError, match="gmm_components must be >= 1"):
        replace(mixture.config, gmm_components=0)


def test_a_gmm_policy_trains_round_trips_its_checkpoint_and_is_scored_on_the_action_it_takes(
    demonstrations, tmp_path
):
    policy = make_gmm_policy(demonstrations, seed=2, gmm_components=3)
    assert policy.out_keys == GMM_KEYS
    initial = {k: v.clone() for k, v in policy.state_dict().items()}
    metrics = train_bc(policy, demonstrations, TINY_TRAINING, run_dir=tmp_path / "run")
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
    loaded = GMMPolicy.from_checkpoint(tmp_path / "run" / "checkpoints")
    trained = loaded.state_dict()
    assert trained.keys() == initial.keys()
    assert not all(torch.equal(trained[k], initial[k]) for k in initial if k.startswith("module.head."))
    assert isinstance(loaded.config, GMMConfig) and loaded.config.gmm_components == 3
    batch = demonstrations.batch(demonstrations.split_frames["val"])
    with torch.no_grad():
        acted = loaded(batch.exclude("action"))
    loc, logits = acted.get(GMM_LOC), acted.get(GMM_LOGITS)
    assert loc.shape == (len(batch), 3, demonstrations.action_dim) and logits.shape == (len(batch), 3)
    assert (acted.get(GMM_SCALE) > 0).all() and loc.abs().max() <= 1
    torch.testing.assert_close(acted.get("action"), most_likely_mean(loc, logits))
    errors = validation_errors(loaded, demonstrations, "val", droppable=())
    expected = ((acted.get("action") - batch.get("action")) ** 2).mean().item()
    assert errors["mse_all"] == pytest.approx(expected, rel=1e-5)


def test_a_gmm_chunk_policy_plays_an_episode_through_bc_env_with_the_ensemble(
    demonstrations, forecaster, tmp_path
):
    k = 4
    policy = make_gmm_policy(demonstrations, action_chunk=k)
    train_bc(policy, demonstrations, TINY_TRAINING, run_dir=tmp_path)
    loaded = GMMPolicy.from_checkpoint(tmp_path / "checkpoints")
    env = bc_env(loaded, forecaster, IMAGE_SIZE, Condition("bursts", "image", "bursts"), seed=0)
    try:
        ((rollout, _),) = list(labelled_episodes(env, loaded, 1, seed=0, max_steps=12))
    finally:
        env.close()
    steps = rollout.shape[0]
    assert rollout.get(GMM_LOC).shape == (steps, k, 5, demonstrations.action_dim)
    chunks = rollout.get(ACTION_CHUNK)
    torch.testing.assert_close(chunks, most_likely_mean(rollout.get(GMM_LOC), rollout.get(GMM_LOGITS)))
    assert rollout.get(PAST_CHUNKS_FILLED).sum(-1).tolist() == [min(t, k - 1) for t in range(steps)]
    torch.testing.assert_close(rollout.get("action"), torch.stack(act_ensemble(list(chunks), 0.01)))
