"""A window cache build SIGKILLed midway resumes where it stopped and gives the cache of a full build.

The large-N version (kill at ~90% of 10k-1M frames) is `benchmarks/cache_scale.py`.
"""

import logging
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from mmf_rl.datasets import WindowDataset, cache
from tests.datasets.conftest import (
    BROKEN_ROWS,
    break_images,
    camera_config,
    differing_files,
    make_camera_dataset,
)
from tests.reliability.conftest import background, output, push_data_config, wait_for

EPISODES = 6  # the recorded push data: one camera, so one video job per episode
DECODED_BEFORE_KILL = 4
# The camera dataset in one process: one job per episode (4) of each image camera, depth's first.
IMAGE_JOBS = 8
# Every depth job and wrist's first, whose undecodable images only the killed build's record names.
IMAGE_JOBS_BEFORE_KILL = 5


def build_killed_after(jobs: int, runner: str, config: str, cache_dir: Path) -> None:
    """Build in a subprocess that SIGKILLs itself when ``cache.<runner>`` starts decoding job
    ``jobs + 1``; ``config``: the expression of the data config (caching in ``cache_dir``). The
    killed build's temp dir is left with those ``jobs`` recorded as finished."""
    script = textwrap.dedent(f"""
        import os, signal
        from mmf_rl.datasets import WindowDataset, cache
        from tests.datasets.conftest import camera_config
        from tests.reliability.conftest import push_data_config

        decode, started = cache.{runner}, []

        def runner(job):
            started.append(job)
            if len(started) > {jobs}:
                os.kill(os.getpid(), signal.SIGKILL)
            return decode(job)

        cache.{runner} = runner
        WindowDataset({config}, num_workers=1)
    """)
    with background([sys.executable, "-c", script]) as process:
        wait_for(lambda: process.poll() is not None, process, 300, "the kill")
    assert process.returncode == -9, output(process)
    [partial] = cache_dir.glob(".building-*")
    assert len((partial / cache.PROGRESS_FILE).read_text().splitlines()) == jobs


def record_jobs(monkeypatch, runner: str) -> list:
    """The jobs ``cache.<runner>`` is called with from now on (they still run), in call order."""
    run, jobs = getattr(cache, runner), []
    monkeypatch.setattr(cache, runner, lambda job: jobs.append(job) or run(job))
    return jobs


def test_a_killed_cache_build_resumes_and_matches_a_full_build(push_copy, tmp_path, monkeypatch, caplog):
    cache_dir = tmp_path / "cache"
    build_killed_after(
        DECODED_BEFORE_KILL,
        "run_video_job",
        f"push_data_config({str(push_copy)!r}, {str(cache_dir)!r})",
        cache_dir,
    )

    decoded = record_jobs(monkeypatch, "run_video_job")
    with caplog.at_level(logging.INFO, logger="mmf_rl"):
        resumed = WindowDataset(push_data_config(push_copy, cache_dir), num_workers=1)
    assert resumed.built and len(decoded) == EPISODES - DECODED_BEFORE_KILL, (
        "only the jobs not done were decoded"
    )
    assert f"resuming an interrupted window cache build in {cache_dir}/.building-" in caplog.text
    assert f"{DECODED_BEFORE_KILL} of {EPISODES} decode jobs already done" in caplog.text
    assert [p.name for p in cache_dir.iterdir()] == [resumed.cache_path.name], (
        "the adopted temp dir became the cache"
    )
    assert not {cache.PROGRESS_FILE, cache.FRAMES_READY} & {p.name for p in resumed.cache_path.iterdir()}
    assert cache.cache_damage(resumed.cache_path) is None

    monkeypatch.undo()
    full = WindowDataset(push_data_config(push_copy, tmp_path / "full"), num_workers=1)
    assert full.built
    a, b = resumed.batch(torch.arange(len(resumed))), full.batch(torch.arange(len(full)))
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    assert all(torch.equal(a.get(k), b.get(k)) for k in a.keys(True, True))
    assert resumed.report["undecodable_files"] == full.report["undecodable_files"] == {}


@pytest.mark.slow
def test_a_killed_build_resumes_after_its_finished_image_jobs(tmp_path, monkeypatch, caplog):
    root = break_images(make_camera_dataset(tmp_path / "images", use_videos=False), BROKEN_ROWS)
    cache_dir = tmp_path / "cache"
    build_killed_after(
        IMAGE_JOBS_BEFORE_KILL,
        "run_image_job",
        f"camera_config({str(root)!r}, {str(cache_dir)!r})",
        cache_dir,
    )

    decoded = record_jobs(monkeypatch, "run_image_job")
    with caplog.at_level(logging.INFO, logger="mmf_rl"), pytest.warns(UserWarning, match="undecodable"):
        resumed = WindowDataset(camera_config(root, cache_dir), num_workers=1)
    assert resumed.built and [(j.modality, j.episodes[0].index) for j in decoded] == [
        ("wrist", 1),
        ("wrist", 2),
        ("wrist", 3),
    ], "only the jobs not done were decoded"
    assert f"{IMAGE_JOBS_BEFORE_KILL} of {IMAGE_JOBS} decode jobs already done" in caplog.text

    monkeypatch.undo()
    with pytest.warns(UserWarning, match="undecodable"):
        full = WindowDataset(camera_config(root, tmp_path / "full"), num_workers=1)
    assert resumed.report == full.report and "episode 0 frame 1" in next(
        iter(full.report["undecodable_files"]["wrist"])
    )
    assert differing_files(resumed.cache_path, full.cache_path) == []
