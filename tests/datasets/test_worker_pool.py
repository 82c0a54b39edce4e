"""Worker processes answering in request order; a dead worker is an error, a dead parent ends them."""

import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from mmf_rl.datasets.worker_pool import WorkerPool

pytestmark = pytest.mark.slow  # every test starts worker processes


def scale(frames: torch.Tensor, factor: int) -> torch.Tensor:
    if factor < 0:
        raise ValueError(f"negative factor {factor}")
    if factor == 0:
        os._exit(3)
    return frames * factor


def make_scale():
    return scale


def pool_children() -> list:
    return [p for p in multiprocessing.active_children() if p.name.startswith("mmf-rl-test-pool")]


def test_results_come_in_request_order_a_result_never_taken_is_skipped_and_closed_workers_exit_cleanly():
    pool = WorkerPool(make_scale, 2, role="test pool", fix="fix it")
    workers = pool_children()
    try:
        frames = torch.arange(6, dtype=torch.uint8)
        tickets = [pool.submit(frames, factor) for factor in (1, 2, -1, 3)]
        assert torch.equal(pool.result(tickets[0]), frames)
        assert torch.equal(pool.result(tickets[1]), frames * 2)
        with pytest.raises(ValueError, match="negative factor -1"):
            pool.result(tickets[2])
        assert torch.equal(pool.result(tickets[3]), frames * 3)
        # Requests go round-robin: 4 and 6 to one worker, 5 and 7 to the other.
        pool.submit(frames, 5)  # its consumer stopped early
        assert torch.equal(pool.result(pool.submit(frames, 6)), frames * 6)
        assert torch.equal(pool.result(pool.submit(frames, 7)), frames * 7)  # 5's answer skipped
        unread = pool.submit(frames, 9)
        _, connection = pool._workers[unread % 2]
        assert connection.poll(60), "no answer"
    finally:
        pool.close()  # with an answer not read: the worker's end of the socket is reset, not at EOF
    assert len(workers) == 2 and [w.exitcode for w in workers] == [0, 0], (
        "a worker ended in an error instead of seeing the pool closed"
    )
    assert not pool_children()


def test_a_dead_worker_is_an_error_naming_it_and_the_pool_closes():
    pool = WorkerPool(make_scale, 1, role="test pool", fix="try the fix")
    ticket = pool.submit(torch.ones(2), 0)  # the worker exits with code 3
    with pytest.raises(
        RuntimeError, match=r"test pool worker process \(pid \d+\) exited with code 3; try the fix"
    ):
        pool.result(ticket)
    assert pool.closed and not pool_children()
    with pytest.raises(RuntimeError, match="pool is closed"):
        pool.submit(torch.ones(2), 1)


def test_a_killed_worker_is_named_by_its_signal():
    pool = WorkerPool(make_scale, 1, role="test pool", fix="try the fix")
    assert torch.equal(pool.result(pool.submit(torch.ones(2), 2)), torch.full((2,), 2.0))
    (worker,) = pool_children()
    os.kill(worker.pid, signal.SIGKILL)
    with pytest.raises(RuntimeError, match=r"was killed by signal 9; try the fix"):
        pool.result(pool.submit(torch.ones(2), 2))
    assert not pool_children()


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie left for a parent that does not reap it counts as gone)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_workers_exit_when_their_parent_is_killed():
    script = (
        "import multiprocessing, time\n"
        "from mmf_rl.datasets.worker_pool import WorkerPool\n"
        "from tests.datasets.test_worker_pool import make_scale\n"
        "if __name__ == '__main__':\n"
        "    pool = WorkerPool(make_scale, 1, role='test pool', fix='')\n"
        "    print(*(p.pid for p in multiprocessing.active_children()), flush=True)\n"
        "    time.sleep(600)\n"
    )
    root = Path(__file__).resolve().parents[2]
    parent = subprocess.Popen([sys.executable, "-c", script], cwd=root, stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(pid) for pid in parent.stdout.readline().split()]
        assert len(workers) == 1 and all(alive(pid) for pid in workers)
    finally:
        parent.kill()  # SIGKILL: no cleanup in the parent
        parent.wait()
    deadline = time.monotonic() + 60
    while any(alive(pid) for pid in workers):
        assert time.monotonic() < deadline, f"workers {workers} outlived their killed parent"
        time.sleep(0.05)
