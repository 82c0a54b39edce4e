"""Fixtures shared by the benchmark scripts' tests."""

from __future__ import annotations

import functools
import shutil
from pathlib import Path

import pytest

# The time limit of the push episodes the closed-loop benchmarks play in their tests (the env's own is
# 50 steps): what those tests check (which policies are built, played and recorded, where their runs
# and results go, what a re-run reuses) does not depend on the episodes' length, and every step renders
# a frame and runs the forecaster and the policy.
TEST_EPISODE_STEPS = 10
# The push envs closed by the benchmarks, by their settings: the next one asked for with the same
# settings is one of these (see `short_push_episodes`).
_CLOSED_PUSH_ENVS: dict[tuple, list] = {}


@functools.cache
def _reused_push_env_class() -> type:
    from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv

    class ReusedPushEnv(MultimodalPushTorchEnv):
        """`MultimodalPushTorchEnv` whose ``close`` keeps it, open, for the next benchmark env of its
        settings (`_CLOSED_PUSH_ENVS`)."""

        settings: tuple = ()

        def close(self, *, raise_if_closed: bool = True) -> None:
            _CLOSED_PUSH_ENVS.setdefault(self.settings, []).append(self)

    return ReusedPushEnv


def _short_push_env(image_size: int = 64, **options):
    """A push env of `TEST_EPISODE_STEPS` steps and these settings: one the benchmarks closed, else a
    new one."""
    settings = (image_size, *sorted(options.items()))
    if closed := _CLOSED_PUSH_ENVS.get(settings):
        return closed.pop()
    env = _reused_push_env_class()(image_size=image_size, max_episode_steps=TEST_EPISODE_STEPS, **options)
    env.settings = settings
    return env


def short_push_episodes(patch: pytest.MonkeyPatch) -> None:
    """Every push env `benchmarks.push.closed_loop.push_env` makes (the episodes the benchmarks play,
    DAgger's and MPC's included) ends after `TEST_EPISODE_STEPS` steps, and is one the benchmarks closed
    when there is one of its settings: a new env costs most of a short episode (its renderer's GL
    context), and every episode starts from a reset with its own seed (`closed_loop.play`,
    `dagger.labelled_episodes`), the same in a used env as in a new one."""
    from benchmarks.push import closed_loop

    patch.setattr(closed_loop, "MultimodalPushTorchEnv", _short_push_env)


@pytest.fixture(scope="session", autouse=True)
def _close_reused_push_envs():
    """At the session's end, the push envs kept for reuse are closed (their GL contexts freed while the
    GL library is still there)."""
    yield
    for envs in _CLOSED_PUSH_ENVS.values():
        while envs:
            env = envs.pop()
            super(type(env), env).close()


@pytest.fixture
def short_episodes(monkeypatch) -> int:
    """`short_push_episodes` for one test; the episodes' time limit."""
    short_push_episodes(monkeypatch)
    return TEST_EPISODE_STEPS


def ethucy_fold_configs(data: Path, into: Path) -> Path:
    """``into`` holding a copy of the fold configs of ``data`` (an `ethucy_cut`'s), which name its
    converted dataset by its absolute path: a ``--data`` directory of its own over the same dataset."""
    into.mkdir(parents=True)
    for config in data.glob("*.yaml"):
        shutil.copy2(config, into / config.name)
    return into


def study_out(tmp_path: Path, cache_dir: Path) -> Path:
    """``tmp_path/out`` for a benchmark's ``--out``, its window cache (``out/cache``, where
    `mmf_rl.compare` keeps it) the session's ``cache_dir`` (`push_cache_dir`): the benchmarks run on the
    recording share its windows, as the tests' own trainings do (the cache's entries are keyed by
    dataset and config)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "cache").symlink_to(cache_dir, target_is_directory=True)
    return out
