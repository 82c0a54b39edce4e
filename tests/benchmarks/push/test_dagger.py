"""DAgger with the scripted pusher as a function of the state as the expert: labels on the
learner's states, the aggregated demonstrations and their forecasts, determinism per seed."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from benchmarks.push.bc_evaluation import bc_env
from benchmarks.push.closed_loop import ScriptedPolicy
from benchmarks.push.dagger import (
    EXPERT_ACTION,
    ROUND_SEEDS,
    demonstration_frames,
    labelled_episodes,
    load_episodes,
    round_seed,
    save_episodes,
)
from benchmarks.push.outage_evaluation import Condition
from mmf_rl import keys
from mmf_rl.envs.scripted import MarkovPusher
from mmf_rl.envs.torchrl_env import GOAL
from mmf_rl.rl import BCPolicy, DemonstrationLoader, EncoderChoice
from mmf_rl.trainers.trainer import seed_everything
from tests.rl.conftest import BC_DROPPABLE

IMAGE_SIZE = 32  # as recorded by `recorded_push_root`
STEPS = 6  # env steps per labelled episode: enough to see the learner and the expert part ways


def tiny_policy(demonstrations, forecasts=None) -> BCPolicy:
    seed_everything(0)
    return BCPolicy.for_demonstrations(
        demonstrations,
        forecasts,
        encoders=EncoderChoice(image_channels=(8, 16)),
        d_model=16,
        hidden=32,
        depth=1,
    ).eval()


def play_labelled(policy, forecaster, episodes: int, seed: int) -> tuple[list[TensorDict], list[dict]]:
    """``episodes`` labelled episodes of ``STEPS`` steps: their rollouts and results."""
    env = bc_env(policy, forecaster, IMAGE_SIZE, Condition("all", None, None), seed)
    try:
        played = list(labelled_episodes(env, policy, episodes, seed, max_steps=STEPS))
    finally:
        env.close()
    return [rollout for rollout, _ in played], [result for _, result in played]


def test_the_labels_are_the_experts_actions_on_the_states_the_learner_visited(
    demonstrations, forecasts, forecaster
):
    policy = tiny_policy(demonstrations, forecasts)
    seed = round_seed(1000, 1)
    (rollout,), (result,) = play_labelled(policy, forecaster, 1, seed)
    assert rollout.shape[0] == result["steps"] == STEPS
    # Asked on the visited states in reverse order, the state-only pusher gives the labels,
    expert = ScriptedPolicy(seed, MarkovPusher())
    for t in reversed(range(STEPS)):
        state = rollout[t].exclude("action", EXPERT_ACTION, "next")
        torch.testing.assert_close(expert(state).get("action"), rollout.get(EXPERT_ACTION)[t])
    # and the learner gives the actions the env was stepped with (its own, not the expert's).
    with torch.no_grad():
        learner = policy(rollout.exclude("action", EXPERT_ACTION, "next")).get("action")
    torch.testing.assert_close(learner, rollout.get("action"))
    assert not torch.allclose(rollout.get("action"), rollout.get(EXPERT_ACTION), atol=1e-3)


def test_the_aggregated_demonstrations_keep_the_recording_and_add_the_labelled_frames(
    demonstrations, forecasts, forecaster
):
    model, stats, _ = forecaster
    rollouts, results = play_labelled(tiny_policy(demonstrations), forecaster, 2, round_seed(1000, 1))
    episodes = [demonstration_frames(rollout, demonstrations.specs) for rollout in rollouts]
    aggregated = demonstrations.with_episodes(episodes)
    n, added = len(demonstrations.goal), sum(r["steps"] for r in results)
    new = torch.arange(n, n + added)

    recorded = demonstrations.split_frames
    assert torch.equal(aggregated.split_frames["train"], torch.cat([recorded["train"], new]))
    assert all(torch.equal(aggregated.split_frames[s], recorded[s]) for s in ("val", "test"))
    frames = recorded["train"]
    assert (aggregated.batch(frames) == demonstrations.batch(frames)).all()
    assert aggregated.normalizer.stats.keys() == demonstrations.normalizer.stats.keys()
    assert all(
        torch.equal(v, demonstrations.normalizer.stats[k]) for k, v in aggregated.normalizer.stats.items()
    )
    # The new frames: the expert's labels, each episode's windows starting at its own first frame.
    torch.testing.assert_close(aggregated.action[new], torch.cat([r.get(EXPERT_ACTION) for r in rollouts]))
    torch.testing.assert_close(aggregated.goal[new], torch.cat([r.get(GOAL) for r in rollouts]))
    second = n + results[0]["steps"]
    assert aggregated.episode_start(new).tolist() == [n] * (second - n) + [second] * (n + added - second)
    image = aggregated.batch(new[:1]).get((keys.HISTORY, "obs", "image"))
    assert bool((image == rollouts[0].get(keys.obs_key("image"))[0]).all()), "padded with the first frame"

    extended = forecasts.extended(aggregated, model, stats)
    assert torch.equal(extended.loc[:n], forecasts.loc) and torch.equal(extended.scale[:n], forecasts.scale)
    assert extended.loc.shape[0] == n + added and torch.isfinite(extended.loc[n:]).all()
    again = type(forecasts).compute(aggregated, model, stats, BC_DROPPABLE, frames=new)
    torch.testing.assert_close(extended.loc[new], again.loc[new])
    loader = DemonstrationLoader(aggregated, "train", 64, dropout={"image": 0.5}, forecasts=extended)
    assert sum(len(batch) for batch in loader) == len(loader) * 64  # every batch served, new frames too


def test_a_frame_unlike_the_recordings_is_refused_with_its_key(demonstrations):
    frames = demonstrations.batch(demonstrations.split_frames["train"][:3])
    with pytest.raises(ValueError, match=r"episode 0 has \('obs', '\w+'\) None.*per frame"):
        demonstrations.with_episodes([frames])
    with pytest.raises(ValueError, match="no episode"):
        demonstrations.with_episodes([])


def test_labelled_episodes_are_determined_by_their_seed(demonstrations, forecaster, tmp_path):
    policy = tiny_policy(demonstrations)
    seed = round_seed(1000, 2)
    assert seed - 1000 == 2 * ROUND_SEEDS
    first, results = play_labelled(policy, forecaster, 2, seed)
    again, results_again = play_labelled(policy, forecaster, 2, seed)
    other, _ = play_labelled(policy, forecaster, 2, seed + 7)
    assert results == results_again
    for a, b in zip(first, again, strict=True):
        assert (a.exclude("next") == b.exclude("next")).all()
    assert not torch.equal(first[0].get(GOAL), other[0].get(GOAL))
    # A round's episodes read back as they were played.
    episodes = [demonstration_frames(rollout, demonstrations.specs) for rollout in first]
    save_episodes(tmp_path / "round", episodes, results)
    loaded, loaded_results = load_episodes(tmp_path / "round")
    assert loaded_results == results
    assert all((a == b).all() for a, b in zip(loaded, episodes, strict=True))
    assert load_episodes(tmp_path / "elsewhere") is None
