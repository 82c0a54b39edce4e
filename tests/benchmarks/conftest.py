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


@pytest.fixture(scope="session")
def ethucy_cut(tmp_path_factory) -> tuple[Path, Path]:
    """``(raw, data)``: a cut of the real ETH/UCY files (`cut_ethucy_raw`: 8 agents within the first 40
    steps of each file) and its conversion, every fold, made once for the session by benchmarks/ethucy.py
    from ``--raw`` as its first invocation makes it (the conversion takes tens of seconds); skipped
    without the files. Both read only: a benchmark run writes its window cache and held-out configs
    beside the fold configs, so a test running one reads a copy of them (`ethucy_fold_configs`)."""
    from benchmarks import ethucy as bench
    from mmf_rl.datasets import ethucy
    from tests.conftest import built_once
    from tests.datasets.conftest import SHARED_DATA, cut_ethucy_raw

    if not (SHARED_DATA / "ethucy" / "trajectories").is_dir():
        pytest.skip(f"ETH/UCY data not at {SHARED_DATA / 'ethucy'} (set MMF_RL_SHARED_DATA)")

    def convert(directory: Path) -> None:
        raw = cut_ethucy_raw(directory, steps=40, agents=8)
        args = bench.parse_args(["--raw", str(raw), "--data", str(directory / "data")])
        assert bench.ensure_data(args, tuple(ethucy.FOLDS)) > 0  # converted: no fold config was there
        assert bench.ensure_data(args, tuple(ethucy.FOLDS)) == 0.0  # found: not converted again

    directory = built_once(tmp_path_factory, "ethucy_cut", convert)
    return directory / "raw", directory / "data"


def ethucy_fold_configs(data: Path, into: Path) -> Path:
    """``into`` holding a copy of the fold configs of ``data`` (an `ethucy_cut`'s), which name its
    converted dataset by its absolute path: a ``--data`` directory of its own over the same dataset."""
    into.mkdir(parents=True)
    for config in data.glob("*.yaml"):
        shutil.copy2(config, into / config.name)
    return into
