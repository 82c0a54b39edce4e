from __future__ import annotations

import pytest
import torch
from torchrl.envs import TransformedEnv

from mmf_rl import keys
from mmf_rl.envs.modality_dropout import (
    GeometricBursts,
    ModalityDropout,
    UniformBursts,
    outage_start_prob,
    replay_outages,
)
from tests.envs.stamp_env import stamp_envs


def dropout_rollout(dropout: ModalityDropout, num_envs: int = 4, steps: int = 120, max_steps: int = 1000):
    env = TransformedEnv(stamp_envs(num_envs, max_steps), dropout)
    try:
        return env.rollout(steps, break_when_any_done=False)
    finally:
        env.close()


def presence_over_time(td, name: str) -> torch.Tensor:
    """``[envs, steps + 1]``: the reset observation, then every step's."""
    return torch.cat([td[keys.present_key(name)][:, :1], td["next", keys.PRESENT, name]], dim=1)


def runs_of_absence(present: torch.Tensor) -> list[int]:
    """Lengths of the runs of False in each row, without runs cut by the rollout's ends."""
    lengths = []
    for row in present.tolist():
        run, started_inside = 0, False
        for i, p in enumerate(row):
            if not p:
                if run == 0:
                    started_inside = i > 0
                run += 1
            else:
                if run and started_inside:
                    lengths.append(run)
                run = 0
    return lengths


def test_dropout_zeroes_data_and_clears_presence():
    td = dropout_rollout(ModalityDropout(["image", "force"], outage_prob=0.2, bursts=UniformBursts(1, 4), seed=0))
    nxt = td["next"]
    for name in ("image", "force"):
        absent = ~nxt[keys.PRESENT, name]
        assert 0 < absent.float().mean() < 1
        obs = nxt[keys.obs_key(name)].flatten(2)
        assert (obs[absent] == 0).all(), "an absent modality carries zeros"
        assert (obs[~absent] != 0).all(), "a present modality keeps its data"
    assert nxt[keys.PRESENT, "proprio"].all(), "modalities not listed never fail"


def test_dropout_is_reproducible_from_its_seed_and_independent_per_env():
    def pattern(seed):
        td = dropout_rollout(ModalityDropout(["image", "force"], outage_prob=0.1, seed=seed), steps=60)
        return torch.stack([presence_over_time(td, m) for m in ("image", "force")])

    first = pattern(3)
    assert torch.equal(first, pattern(3))
    assert not torch.equal(first, pattern(4))
    assert not torch.equal(first[:, 0], first[:, 1]), "each env draws its own outages"


@pytest.mark.parametrize("bursts", [UniformBursts(2, 4), GeometricBursts(3.0)])
def test_dropout_bursts_have_the_configured_lengths(bursts):
    td = dropout_rollout(ModalityDropout(["force"], outage_prob=0.15, bursts=bursts, seed=1), num_envs=4, steps=300)
    lengths = torch.tensor(runs_of_absence(presence_over_time(td, "force")))
    assert len(lengths) > 40
    if isinstance(bursts, UniformBursts):
        assert set(lengths.tolist()) == {2, 3, 4}
    else:
        assert lengths.min() == 1 and lengths.max() > 6
        assert abs(lengths.float().mean().item() - 3.0) < 0.6


def test_replay_outages_gives_each_modality_its_measured_fraction_and_bursts():
    outages = {"force": {"fraction": 0.2, "mean_burst": 4.0}, "image": {"fraction": 0.05, "mean_burst": 2.0},
               "proprio": {"fraction": 0.0, "mean_burst": 0.0}}
    replay = replay_outages(outages, seed=3)
    assert [t.modalities for t in replay] == [["force"], ["image"]]  # nothing to replay for proprio
    td = dropout_rollout(replay, num_envs=4, steps=600)
    for name in ("force", "image"):
        present = presence_over_time(td, name)
        assert abs((~present).float().mean().item() - outages[name]["fraction"]) < 0.04, name
        lengths = torch.tensor(runs_of_absence(present)).float()
        assert abs(lengths.mean().item() - outages[name]["mean_burst"]) < 0.25 * outages[name]["mean_burst"], name
    assert presence_over_time(td, "proprio").all()
    assert outage_start_prob(0.2, 4.0) == pytest.approx(0.0625)  # 4 / (4 + 1 / p) = 0.2
    with pytest.raises(ValueError, match="no modality .* has outages to replay"):
        replay_outages({"proprio": outages["proprio"]})


def test_dropout_per_episode_holds_for_the_whole_episode():
    td = dropout_rollout(ModalityDropout(["image"], outage_prob=0.5, per="episode", seed=0),
                         num_envs=8, steps=40, max_steps=10)
    present = presence_over_time(td, "image")  # 4 episodes of 10 steps per env
    steps = torch.arange(present.shape[1])
    for env in range(present.shape[0]):
        for episode in range(4):
            # Step 10 of an episode is its terminal observation; the reset observation follows in the root td.
            chunk = present[env, (steps > 10 * episode) & (steps <= 10 * episode + 9)]
            assert chunk.all() or not chunk.any()
    assert 0 < present.float().mean() < 1


def test_dropout_reset_clears_the_outages_of_the_envs_that_reset():
    env = TransformedEnv(stamp_envs(2), ModalityDropout(["force"], outage_prob=1.0, bursts=UniformBursts(5, 5)))
    try:
        td = env.reset()
        # An outage starts at the reset observation: 5 absent observations, then one present.
        for _ in range(3):
            td = env.step(env.rand_action(td))["next"]
        td["_reset"] = torch.tensor([[True], [False]])
        td = env.reset(td)
        present = [td[keys.present_key("force")].tolist()]
        for _ in range(5):
            td = env.step(env.rand_action(td))["next"]
            present.append(td[keys.present_key("force")].tolist())
        # env 0 restarted its 5-step outage at the reset; env 1 finished its outage 2 steps later.
        assert [p[0] for p in present] == [False] * 5 + [True]
        assert [p[1] for p in present] == [False, False, True, False, False, False]
    finally:
        env.close()
