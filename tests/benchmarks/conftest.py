"""Fixtures shared by the benchmark scripts' tests."""

from __future__ import annotations

import functools

import pytest

# The time limit of the push episodes the closed-loop benchmarks play in their tests (the env's own is
# 50 steps): what those tests check (which policies are built, played and recorded, where their runs
# and results go, what a re-run reuses) does not depend on the episodes' length, and every step renders
# a frame and runs the forecaster and the policy.
TEST_EPISODE_STEPS = 10


def short_push_episodes(patch: pytest.MonkeyPatch) -> None:
    """Every push env `benchmarks.push.closed_loop.push_env` makes (the episodes the benchmarks play,
    DAgger's included) ends after `TEST_EPISODE_STEPS` steps."""
    from benchmarks.push import closed_loop
    from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv

    short = functools.partial(MultimodalPushTorchEnv, max_episode_steps=TEST_EPISODE_STEPS)
    patch.setattr(closed_loop, "MultimodalPushTorchEnv", short)


@pytest.fixture
def short_episodes(monkeypatch) -> int:
    """`short_push_episodes` for one test; the episodes' time limit."""
    short_push_episodes(monkeypatch)
    return TEST_EPISODE_STEPS
