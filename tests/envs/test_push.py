from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest

from mmf_rl.envs import ENV_ID
from mmf_rl.envs.push import FORCE_NAMES, OBJECT_POSE_NAMES, PROPRIO_NAMES, MultimodalPushEnv
from mmf_rl.envs.scripted import ScriptedPusher, episode_generator, reset_for_push, rollout
from tests.envs.conftest import IMAGE_SIZE


def test_observation_has_every_sensor(push_env):
    obs, _ = push_env.reset(seed=0)
    assert obs["image"].shape == (IMAGE_SIZE, IMAGE_SIZE, 3) and obs["image"].dtype == np.uint8
    assert obs["image"].std() > 10, "the camera should see a scene, not a flat colour"
    assert obs["force"].shape == (len(FORCE_NAMES),)
    assert obs["proprio"].shape == (len(PROPRIO_NAMES),)
    assert obs["object_pose"].shape == (len(OBJECT_POSE_NAMES),)
    np.testing.assert_allclose(obs["object_pose"][:3], obs["achieved_goal"])
    assert np.linalg.norm(obs["object_pose"][3:]) == pytest.approx(1.0)
    assert push_env.observation_space.contains(obs)
    obs, *_ = push_env.step(push_env.action_space.sample())
    assert push_env.observation_space.contains(obs)


def test_control_rate_is_fetchpush_25_hz(push_env):
    assert round(1.0 / push_env.dt) == 25


def test_force_is_the_push_on_the_object(push_env):
    """Pushing moves the object along the force the gripper applies to it."""
    episode = rollout(push_env, seed=0, episode_index=0, steps=50)
    force = episode["force"][:-1, :2]
    displacement = np.diff(episode["object_pose"][:, :2], axis=0)
    pushing = (np.linalg.norm(force, axis=1) > 1.0) & (np.linalg.norm(displacement, axis=1) > 1e-3)
    assert pushing.sum() >= 3, "the scripted pusher should be in contact for several steps"
    alignment = np.sum(force[pushing] * displacement[pushing], axis=1)
    assert np.mean(alignment > 0) > 0.8
    assert np.all(episode["force"][0] == 0), "no contact before the first action"


def test_force_sums_all_physics_substeps(push_env):
    """Contacts read once after `step` miss pushes that the wrench summed over sub-steps catches."""
    rng = episode_generator(0, 0)
    obs, _ = reset_for_push(push_env, rng)
    pusher = ScriptedPusher()
    pusher.reset(rng)
    summed, read_after_step = 0, 0
    for _ in range(50):
        obs, *_ = push_env.step(pusher.act(obs))
        summed += np.any(obs["force"] != 0)
        read_after_step += np.any(push_env.gripper_object_wrench() != 0)
    assert summed > read_after_step


def test_named_model_camera_renders_another_view(push_env):
    env = MultimodalPushEnv(image_size=IMAGE_SIZE, camera="external_camera_0")
    try:
        side, _ = env.reset(seed=0)
    finally:
        env.close()
    front, _ = push_env.reset(seed=0)
    assert side["image"].shape == front["image"].shape
    assert np.abs(side["image"].astype(int) - front["image"]).mean() > 10


def test_renders_its_own_view_beside_other_envs(push_env):
    before, _ = push_env.reset(seed=0)
    other = MultimodalPushEnv(image_size=IMAGE_SIZE, camera="top")
    other.reset(seed=1)
    other.close()
    after, _ = push_env.reset(seed=0)
    np.testing.assert_array_equal(before["image"], after["image"])


def test_unknown_camera_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown camera 'nope'.*front"):
        MultimodalPushEnv(camera="nope")


def test_registered_gymnasium_id():
    env = gymnasium.make(ENV_ID, image_size=IMAGE_SIZE)
    try:
        obs, _ = env.reset(seed=0)
        assert obs["image"].shape == (IMAGE_SIZE, IMAGE_SIZE, 3)
        assert env.spec.max_episode_steps == 50
    finally:
        env.close()


@pytest.mark.slow
def test_importing_the_envs_prints_no_adroit_note():
    """gymnasium-robotics' note on its Adroit envs is held back; its other output is not."""
    code = (
        "import sys, mmf_rl.envs, farama_notifications; "
        "print('kept' if 'gymnasium_robotics' in farama_notifications.notifications else 'lost', "
        "file=sys.stderr)"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "Adroit" not in result.stderr and result.stderr.endswith("kept\n")
