"""A window cache build SIGKILLed midway resumes where it stopped and gives the cache of a full build.

The large-N version (kill at ~90% of 10k-1M frames) is `benchmarks/cache_scale.py`.
"""

import logging
import sys
import textwrap

import torch

from mmf_rl.datasets import WindowDataset, cache
from tests.reliability.conftest import background, output, push_data_config, wait_for

EPISODES = 6  # the recorded push data: one camera, so one video job per episode
DECODED_BEFORE_KILL = 4


def build_killed_after(jobs: int, root, cache_dir) -> str:
    """Build in a subprocess that SIGKILLs itself when it starts decoding job ``jobs + 1``."""
    script = textwrap.dedent(f"""
        import os, signal
        from mmf_rl.datasets import WindowDataset, cache
        from tests.reliability.conftest import push_data_config

        decode, started = cache.run_video_job, []

        def run_video_job(job):
            started.append(job)
            if len(started) > {jobs}:
                os.kill(os.getpid(), signal.SIGKILL)
            return decode(job)

        cache.run_video_job = run_video_job
        WindowDataset(push_data_config({str(root)!r}, {str(cache_dir)!r}), num_workers=1)
    """)
    with background([sys.executable, "-c", script]) as process:
        wait_for(lambda: process.poll() is not None, process, 300, "the kill")
    assert process.returncode == -9, output(process)
    return output(process)


def test_a_killed_cache_build_resumes_and_matches_a_full_build(push_copy, tmp_path, monkeypatch, caplog):
    cache_dir = tmp_path / "cache"
    build_killed_after(DECODED_BEFORE_KILL, push_copy, cache_dir)
    [partial] = cache_dir.glob(".building-*")
    assert len((partial / cache.PROGRESS_FILE).read_text().splitlines()) == DECODED_BEFORE_KILL

    decode, decoded = cache.run_video_job, []
    monkeypatch.setattr(cache, "run_video_job", lambda job: decoded.append(job) or decode(job))
    with caplog.at_level(logging.INFO, logger="mmf_rl"):
        resumed = WindowDataset(push_data_config(push_copy, cache_dir), num_workers=1)
    assert resumed.built and len(decoded) == EPISODES - DECODED_BEFORE_KILL, (
        "only the jobs not done were decoded"
    )
    assert f"resuming an interrupted window cache build in {cache_dir}/.building-" in caplog.text
    assert f"{DECODED_BEFORE_KILL} of {EPISODES} video jobs already decoded" in caplog.text
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
