from __future__ import annotations

import os

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs import ParallelEnv, SerialEnv
from torchrl.envs.utils import check_env_specs

from mmf_rl import keys
from mmf_rl.envs import ENV_ID
from mmf_rl.envs.torchrl_env import MODALITIES, MultimodalPushTorchEnv
from tests.envs.conftest import IMAGE_SIZE


@pytest.fixture(scope="module")
def env():
    env = MultimodalPushTorchEnv(image_size=IMAGE_SIZE)
    yield env
    env.close()


def test_single_env_passes_check_env_specs(env):
    check_env_specs(env, seed=0)
    td = env.reset()
    assert td[keys.obs_key("image")].shape == (3, IMAGE_SIZE, IMAGE_SIZE)
    assert td[keys.obs_key("image")].dtype == torch.uint8
    assert td[keys.obs_key("force")].shape == (6,) and td[keys.obs_key("force")].dtype == torch.float32
    assert td[keys.obs_key("proprio")].shape == (17,) and td[keys.obs_key("proprio")].dtype == torch.float32
    assert all(td[keys.present_key(m)].item() for m in MODALITIES)


def test_serial_env_passes_check_env_specs():
    env = SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE))
    try:
        check_env_specs(env, seed=0)
        td = env.rollout(3, break_when_any_done=False)
        assert td[keys.PRESENT, "image"].shape == (2, 3)
        assert td["next", keys.OBS, "image"].shape == (2, 3, 3, IMAGE_SIZE, IMAGE_SIZE)
        assert not torch.equal(td["object_pose"][0, 0], td["object_pose"][1, 0]), (
            "envs start in different states"
        )
    finally:
        env.close()


def test_observation_is_the_gym_env_observation_channels_first(env):
    """Same seed: the TorchRL observation is the gymnasium env's, image transposed to CHW."""
    gym_env = gymnasium.make(ENV_ID, image_size=IMAGE_SIZE)
    min_start_distance = env.min_start_distance
    try:
        obs, _ = gym_env.reset(seed=7)
        env.min_start_distance = 0.0  # take gymnasium's first draw, as the raw env does
        env.set_seed(7)
        td = env.reset()
        np.testing.assert_array_equal(td[keys.obs_key("image")].numpy(), obs["image"].transpose(2, 0, 1))
        np.testing.assert_allclose(td[keys.obs_key("proprio")].numpy(), obs["proprio"], rtol=1e-6)
        np.testing.assert_allclose(td["object_pose"].numpy(), obs["object_pose"], rtol=1e-6)
        np.testing.assert_allclose(td["goal"].numpy(), obs["desired_goal"], rtol=1e-6)
    finally:
        env.min_start_distance = min_start_distance
        gym_env.close()


def test_reward_is_minus_planar_distance_and_time_limit_ends_episode():
    env = MultimodalPushTorchEnv(image_size=IMAGE_SIZE, max_episode_steps=4)
    try:
        env.set_seed(1)
        td = env.rollout(10, break_when_any_done=True)
        nxt = td["next"]
        distance = torch.linalg.vector_norm(nxt["object_pose"][:, :2] - nxt["goal"][:, :2], dim=-1)
        torch.testing.assert_close(nxt["reward"].squeeze(-1), -distance)
        assert td.shape == (4,), "the 4-step time limit ends the rollout"
        assert nxt["truncated"][-1].item() and nxt["done"][-1].item() and not nxt["done"][:-1].any()
        assert (distance >= 0.05).all(), "reset starts the object away from the goal"
    finally:
        env.close()


def test_seed_makes_resets_reproducible(env):
    env.set_seed(3)
    first = env.reset()["object_pose"]
    env.set_seed(3)
    assert torch.equal(env.reset()["object_pose"], first)


@pytest.mark.skipif(
    not os.environ.get("MMF_RL_PARALLEL_TESTS"),
    reason="spawns 2 processes that each import torch and MuJoCo (~20-70 s); set MMF_RL_PARALLEL_TESTS=1",
)
def test_parallel_env_with_spawn():
    env = ParallelEnv(
        2, MultimodalPushTorchEnv, create_env_kwargs={"image_size": IMAGE_SIZE}, mp_start_method="spawn"
    )
    try:
        env.set_seed(0)
        td = env.rollout(3, break_when_any_done=False)
        assert td["next", keys.OBS, "image"].shape == (2, 3, 3, IMAGE_SIZE, IMAGE_SIZE)
        assert td["next", keys.OBS, "image"].float().std() > 10, "each worker renders its own scene"
    finally:
        env.close()
