"""One of two DDP ranks SIGKILLed mid-training: the run ends with a clear error, quickly, no hang."""

import os
import signal
import sys
import time
from pathlib import Path

from benchmarks.kill_loop import run_overrides
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.models import load_trained_model
from tests.reliability.conftest import background, free_port, output, wait_for

DIST_TIMEOUT_S = 30


def worker_pids(launcher_pid: int) -> dict[int, int]:
    """rank -> pid of torchrun's worker processes (read from their environment)."""
    ranks = {}
    for pid in Path(f"/proc/{launcher_pid}/task/{launcher_pid}/children").read_text().split():
        environ = dict(
            line.split("=", 1) for line in Path(f"/proc/{pid}/environ").read_text().split("\0") if "=" in line
        )
        ranks[int(environ["RANK"])] = int(pid)
    return ranks


def test_a_killed_rank_ends_the_run_with_a_clear_error_well_within_the_timeout(
    recorded_push_root, push_cache_dir, tmp_path
):
    checkpoints = tmp_path / "ddp" / "checkpoints"
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--nproc_per_node=2",
        f"--master_port={free_port()}",
        "--master_addr=127.0.0.1",
        "-m",
        "mmf_rl.cli",
        "train",
        *run_overrides(recorded_push_root, push_cache_dir, tmp_path / "ddp", total_steps=100_000),
    ]
    with background(command, MMF_RL_DIST_TIMEOUT=str(DIST_TIMEOUT_S)) as launcher:
        wait_for(lambda: any(checkpoints.glob("step_*")), launcher, 300, "a checkpoint")
        workers = worker_pids(launcher.pid)
        assert sorted(workers) == [0, 1]
        killed_at = time.monotonic()
        os.kill(workers[1], signal.SIGKILL)
        wait_for(lambda: launcher.poll() is not None, launcher, DIST_TIMEOUT_S, "end of torchrun")
    elapsed = time.monotonic() - killed_at
    log = output(launcher)
    assert launcher.returncode != 0
    assert elapsed < DIST_TIMEOUT_S / 2, f"the surviving rank took {elapsed:.0f} s to stop"
    # torchrun's report names the dead rank and its signal ...
    assert "Root Cause" in log and "rank      : 1" in log and "Signal 9 (SIGKILL)" in log
    # ... and rank 0 either says why in one line or was stopped by torchrun first, never a traceback.
    assert "mmf-rl train: error: rank 0 of 2 stopped" in log or "Signal 15 (SIGTERM)" in log, log[-3000:]
    assert "[rank0]: Traceback" not in log, log[-3000:]
    # What the two ranks of one node (torchrun --nproc_per_node=2) checkpointed before the kill: one
    # run, with both ranks' generators and the plain model's weights (no DDP wrapper names).
    checkpoint = load_checkpoint(checkpoints)
    assert checkpoint.step >= 1 and checkpoint.meta["world_size"] == 2
    assert len(checkpoint.trainer_state["rng"]) == 2
    load_trained_model(checkpoints)
