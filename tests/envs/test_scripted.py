from __future__ import annotations

import numpy as np

from mmf_rl.envs.scripted import MIN_START_DISTANCE, PusherStyle, episode_generator, rollout


def test_rollout_shapes(push_env):
    episode = rollout(push_env, seed=0, episode_index=0, steps=7)
    assert episode["image"].shape == (7, 32, 32, 3) and episode["image"].dtype == np.uint8
    for key, width in (("force", 6), ("proprio", 17), ("object_pose", 7), ("goal", 3), ("action", 4)):
        assert episode[key].shape == (7, width) and episode[key].dtype == np.float32, key
    assert np.all(np.abs(episode["action"]) <= 1.0)
    start = np.linalg.norm(episode["goal"][0, :2] - episode["object_pose"][0, :2])
    assert start >= MIN_START_DISTANCE


def test_episode_depends_only_on_seed_and_index(push_env):
    first = rollout(push_env, seed=5, episode_index=3, steps=30)
    rollout(push_env, seed=5, episode_index=0, steps=10)  # other episodes in between change nothing
    again = rollout(push_env, seed=5, episode_index=3, steps=30)
    for key in first:
        np.testing.assert_array_equal(first[key], again[key], err_msg=key)
    other = rollout(push_env, seed=6, episode_index=3, steps=30)
    assert not np.array_equal(first["object_pose"], other["object_pose"])


def test_pusher_reaches_the_goal(push_env):
    episodes = [rollout(push_env, seed=0, episode_index=i, steps=50) for i in range(4)]
    assert sum(e["success"][-1] for e in episodes) >= 3
    for e in episodes:
        start = np.linalg.norm(e["goal"][0, :2] - e["object_pose"][0, :2])
        end = np.linalg.norm(e["goal"][-1, :2] - e["object_pose"][-1, :2])
        assert end < start
        assert np.any(e["force"] != 0), "every episode pushes"


def test_styles_vary_between_episodes():
    styles = {PusherStyle.sample(episode_generator(0, i)) for i in range(10)}
    assert len(styles) == 10


def test_exploration_adds_seeded_random_bursts_and_zero_changes_nothing(push_env):
    plain = rollout(push_env, seed=2, episode_index=1, steps=40)
    np.testing.assert_array_equal(plain["action"], rollout(push_env, 2, 1, 40, exploration=0.0)["action"])
    explored = rollout(push_env, seed=2, episode_index=1, steps=40, exploration=0.3)
    np.testing.assert_array_equal(explored["action"], rollout(push_env, 2, 1, 40, exploration=0.3)["action"])
    actions = explored["action"]
    # A burst repeats one move exactly for 2-7 steps; the pusher's noisy moves never repeat.
    repeats = np.all(actions[1:] == actions[:-1], axis=1)
    runs, length = [], 0
    for same in repeats:
        if same:
            length += 1
        elif length:
            runs.append(length + 1)
            length = 0
    assert runs and all(2 <= r <= 7 for r in runs[:-1]), runs
    assert not np.any(
        np.all(plain["action"][1:] == plain["action"][:-1], axis=1) & (plain["action"][1:, :3] != 0).any(1)
    )


def test_exploration_must_be_a_probability():
    import pytest

    from mmf_rl.envs.scripted import ScriptedPusher

    with pytest.raises(ValueError, match=r"exploration must be a probability in \[0, 1\], found 1.5"):
        ScriptedPusher(exploration=1.5)


class DrawnDirection:
    """An `Actor`: each episode pushes one direction drawn from its generator; counts its calls."""

    def reset(self, rng):
        self.action = np.r_[rng.uniform(-1.0, 1.0, 3), 0.0].astype(np.float32)
        self.observations = []

    def act(self, obs):
        self.observations.append(obs["proprio"].copy())
        return self.action


def test_an_actor_acts_in_place_of_the_pusher_and_depends_only_on_seed_and_index(push_env):
    actor = DrawnDirection()
    episode = rollout(push_env, seed=4, episode_index=2, steps=12, actor=actor)
    assert len(actor.observations) == 12
    np.testing.assert_array_equal(episode["action"], np.tile(actor.action, (12, 1)))
    np.testing.assert_array_equal(np.stack(actor.observations).astype(np.float32), episode["proprio"])
    again = rollout(push_env, seed=4, episode_index=2, steps=12, actor=DrawnDirection())
    for key in episode:
        np.testing.assert_array_equal(episode[key], again[key], err_msg=key)
    scripted = rollout(push_env, seed=4, episode_index=2, steps=12)
    np.testing.assert_array_equal(scripted["object_pose"][0], episode["object_pose"][0])  # same start
    assert not np.array_equal(scripted["action"], episode["action"])


def test_exploration_bursts_override_an_actor_that_still_sees_every_step(push_env):
    actor = DrawnDirection()
    explored = rollout(push_env, seed=2, episode_index=1, steps=40, exploration=0.3, actor=actor)
    assert len(actor.observations) == 40, "the actor observes every step, bursts included"
    bursts = ~np.all(explored["action"] == actor.action, axis=1)
    assert bursts.any() and not bursts.all()
    again = rollout(push_env, seed=2, episode_index=1, steps=40, exploration=0.3, actor=DrawnDirection())
    np.testing.assert_array_equal(explored["action"], again["action"])
