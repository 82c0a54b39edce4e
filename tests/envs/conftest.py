"""Fixtures for the simulated push env: one env (and one GL context) per test module."""

from __future__ import annotations

import pytest

from mmf_rl.envs.push import MultimodalPushEnv

IMAGE_SIZE = 32


@pytest.fixture(scope="module")
def push_env(request):
    """The module's env, at its ``IMAGE_SIZE`` when it sets one (e.g. smaller where no test reads the
    frames: rendering is most of a step), else this file's."""
    env = MultimodalPushEnv(image_size=getattr(request.module, "IMAGE_SIZE", IMAGE_SIZE))
    yield env
    env.close()
