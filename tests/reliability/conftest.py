"""Fixtures for the fault-injection tests: subprocess helpers, a private copy of the recording."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch

from benchmarks.kill_loop import subprocess_env
from mmf_rl.datasets import DataConfig

POLL_S = 0.02


@contextlib.contextmanager
def single_thread():
    """In-process training with the kernels of a single-threaded subprocess (OMP_NUM_THREADS=1)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def background(command: list[str], **env):
    """A subprocess writing its output to a temp file, always killed and reaped on exit.

    `output(process)` reads what it wrote, during the block and after it.
    """
    with tempfile.TemporaryFile("w+") as log:
        process = subprocess.Popen(
            command,
            env={**subprocess_env(), **env},
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        process.log = log
        try:
            yield process
        finally:
            # Its own session: children that outlive it (torchrun's workers) go too.
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            process.final_output = output(process)


def output(process) -> str:
    if hasattr(process, "final_output"):
        return process.final_output
    process.log.seek(0)
    return process.log.read()


def wait_for(condition, process, timeout_s: float, what: str) -> None:
    """Poll ``condition()`` while ``process`` runs; fail with its output if it ends or time runs out."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if process.poll() is not None:
            pytest.fail(
                f"the process ended (exit {process.returncode}) before {what}:\n{output(process)[-3000:]}"
            )
        if time.monotonic() > deadline:
            pytest.fail(f"no {what} after {timeout_s} s:\n{output(process)[-3000:]}")
        time.sleep(POLL_S)


def running(pid: int) -> bool:
    """Alive and not a zombie (a container's init may never reap an orphan)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def kill_parent_and_check_workers_end(process, workers: list[int], what: str) -> None:
    """SIGKILL ``process`` alone (it cannot stop its workers) and wait up to a minute for every one of
    ``workers`` to notice and end."""
    process.kill()
    process.wait()
    deadline = time.monotonic() + 60
    while any(map(running, workers)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(running, workers)), f"a worker outlived its killed {what}"


def cli_command(*args: str) -> list[str]:
    return [sys.executable, "-m", "mmf_rl.cli", *args]


@pytest.fixture
def push_copy(recorded_push_root, tmp_path) -> Path:
    """A private copy of the recorded push dataset, for tests that damage its files."""
    return Path(shutil.copytree(recorded_push_root, tmp_path / "push"))


def edit_frames(root: Path, edit) -> None:
    """Rewrite the dataset's frame table: ``edit(frames)`` changes a pandas DataFrame in place.

    Vector features are columns of numpy arrays, one per frame; the file keeps its schema.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    [path] = (root / "data").rglob("*.parquet")
    table = pq.read_table(path)
    frames = table.to_pandas()
    edit(frames)
    pq.write_table(pa.Table.from_pandas(frames, schema=table.schema, preserve_index=False), path)


def push_data_config(root: Path, cache_dir: Path, **overrides) -> DataConfig:
    """The push data config of `tests.conftest.push_train_overrides`, as a `DataConfig`."""
    return DataConfig.from_dict(
        {
            "root": str(root),
            "cache_dir": str(cache_dir),
            "history": 4,
            "horizon": 3,
            "image_size": [32, 32],
            "include_target_past": True,
            "split_fractions": [0.5, 0.25, 0.25],
            "modalities": {
                "image": "observation.images.front",
                "force": "observation.force",
                "proprio": "observation.state",
            },
            "target": {"feature": "observation.object_pose", "dims": [0, 1], "relative": True},
            **overrides,
        }
    )
