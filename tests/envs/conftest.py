"""Fixtures for the simulated push env: one env (and one GL context) per test module."""

from __future__ import annotations

import pytest

from mmf_rl.envs.push import MultimodalPushEnv

IMAGE_SIZE = 32


@pytest.fixture(scope="module")
def push_env():
    env = MultimodalPushEnv(image_size=IMAGE_SIZE)
    yield env
    env.close()
