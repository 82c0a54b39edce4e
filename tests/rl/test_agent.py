"""`MPCActor` / `PushMPCAgent`: the MPC agent the recorder drives with gymnasium observations."""

import pickle

import numpy as np
import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE
from mmf_rl.rl import PushMPCAgent, PushObjective, SequenceCEMPlanner
from mmf_rl.rl.agent import MPCActor

IMAGE_SIZE = 32
SIZES = {"num_candidates": 16, "num_iterations": 2, "num_elites": 4}


def gymnasium_observation(td) -> dict[str, np.ndarray]:
    """`MultimodalPushEnv`'s observation dict behind one step of `MultimodalPushTorchEnv`."""
    return {
        "image": td.get(keys.obs_key("image")).permute(1, 2, 0).numpy(),
        "force": td.get(keys.obs_key("force")).numpy(),
        "proprio": td.get(keys.obs_key("proprio")).numpy(),
        "object_pose": td.get(OBJECT_POSE).numpy(),
        "desired_goal": td.get(GOAL).numpy(),
    }


def test_actor_acts_as_the_planner_in_a_transformed_env(push_world_model, push_history_env):
    """Fed the same observations, the actor's window and warm start give the planner's actions in
    the TorchRL env (HistoryWindow + InitTracker), step for step, over two episodes."""
    planner = SequenceCEMPlanner(push_world_model, PushObjective(), push_history_env.action_spec, **SIZES)
    push_history_env.set_seed(3)
    episodes = []
    for number in range(2):
        # What the actor's reset does with the episode's generator.
        planner.generator.manual_seed(int(np.random.default_rng(number).integers(2**63)))
        episodes.append(push_history_env.rollout(4, planner, break_when_any_done=False))

    actor = MPCActor(push_world_model, PushObjective(), IMAGE_SIZE, **SIZES)
    for number, episode in enumerate(episodes):
        actor.reset(np.random.default_rng(number))
        for t in range(episode.shape[0]):
            action = actor.act(gymnasium_observation(episode[t]))
            window = actor.history.window()[0]
            for key in window.keys(True, True):
                torch.testing.assert_close(
                    window.get(key), episode[t].get((keys.HISTORY, *key)), rtol=0, atol=0
                )
            assert action.dtype == np.float32 and action.shape == (4,)
            np.testing.assert_array_equal(action, episode[t].get("action").numpy(), err_msg=f"{number}, {t}")


def test_reset_makes_an_episode_depend_on_its_generator_only(push_world_model, push_history_env):
    observation = gymnasium_observation(push_history_env.reset())
    actor = MPCActor(push_world_model, PushObjective(), IMAGE_SIZE, **SIZES)
    first = []
    for _ in range(2):
        actor.reset(np.random.default_rng(0))
        first.append([actor.act(observation) for _ in range(3)])
    np.testing.assert_array_equal(np.stack(first[0]), np.stack(first[1]))
    actor.reset(np.random.default_rng(1))
    assert not np.array_equal(actor.act(observation), first[0][0])


def test_agent_factory_pickles_and_builds_an_actor(push_world_model_run):
    agent = PushMPCAgent(
        push_world_model_run / "checkpoints", image_size=IMAGE_SIZE, uncertainty_weight=0.3, **SIZES
    )
    copy = pickle.loads(pickle.dumps(agent))
    assert copy == agent
    actor = copy()
    assert isinstance(actor, MPCActor) and actor.planner.num_candidates == SIZES["num_candidates"]
    assert actor.planner.objective.uncertainty_weight == 0.3
    assert str(push_world_model_run / "checkpoints") in str(agent)


def test_agent_factory_fails_in_the_caller_naming_the_path(tmp_path):
    missing = tmp_path / "no_such_run"
    with pytest.raises(CheckpointError, match=str(missing)):
        PushMPCAgent(missing)
