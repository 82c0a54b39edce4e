"""Shard workers: results and progress come back in order, a failure or a death names its shard
and stops the others, and the workers end with their parent."""

import os
import signal
import sys
import threading
from pathlib import Path

import pytest

from mmf_rl.shards import ShardError, run_shards

pytestmark = pytest.mark.slow  # every test spawns shard workers

# Shard workers: module functions, so that a spawned process imports them by name (this module
# imports little at its top, so that the spawned processes start fast).


def count(start: int, stop: int, progress) -> list[int]:
    for value in range(start, stop):
        progress(value)
    return [start, stop]


def count_in_threads(start: int, stop: int, progress) -> list[int]:
    """`count`'s result, and the worker's torch thread count."""
    import torch

    return [*count(start, stop, progress), torch.get_num_threads()]


def sleep_forever(directory: str, progress) -> None:
    """Leave this process's PID in ``directory``, then wait for a stop that only a signal brings."""
    (Path(directory) / f"{os.getpid()}.pid").write_text("")
    threading.Event().wait()


def fail_or_sleep(fails: bool, directory: str, progress) -> None:
    if fails:
        raise ValueError("bad part 'zara01'")
    sleep_forever(directory, progress)


class Unpicklable(Exception):
    def __init__(self, part: str, reason: str):  # the parent cannot rebuild it from its args
        super().__init__(f"{part}: {reason}")


def raise_unpicklable(fails: bool, progress) -> None:
    if fails:
        raise Unpicklable("zara01", "broken")


def die(how: str, progress) -> None:
    progress("started")
    if how == "SIGKILL":
        os.kill(os.getpid(), signal.SIGKILL)
    if how == "exit":
        os._exit(3)
    raise KeyboardInterrupt


# ---------------------------------------------------------------------------------------------------


def test_results_and_progress_come_back_per_shard_in_order_from_workers_of_one_torch_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "3")  # what torch would run in a spawned process
    messages = []
    results = run_shards(count_in_threads, [(0, 3), (10, 12)], lambda shard, m: messages.append((shard, m)))
    assert [result[:2] for result in results] == [[0, 3], [10, 12]]
    assert [m for s, m in messages if s == 0] == [0, 1, 2]
    assert [m for s, m in messages if s == 1] == [10, 11]
    assert [result[2] for result in results] == [1, 1], "each worker runs one torch thread"


def test_a_worker_that_raises_is_named_and_the_others_are_stopped(tmp_path):
    from tests.reliability.conftest import running

    with pytest.raises(ShardError) as raised:
        # Shard 0 never ends by itself: run_shards returns only because it stopped it.
        run_shards(fail_or_sleep, [(False, str(tmp_path)), (True, str(tmp_path))])
    assert raised.value.shard == 1 and raised.value.detail == "ValueError: bad part 'zara01'"
    assert isinstance(raised.value.error, ValueError)
    assert not [int(p.stem) for p in tmp_path.glob("*.pid") if running(int(p.stem))]


def test_an_exception_the_parent_cannot_rebuild_is_still_named():
    with pytest.raises(ShardError) as raised:
        run_shards(raise_unpicklable, [(False,), (True,)])
    assert raised.value.shard == 1 and raised.value.detail == "Unpicklable: zara01: broken"
    assert raised.value.error is None


@pytest.mark.parametrize(
    ("how", "reported"),
    [
        ("SIGKILL", r"was killed by SIGKILL \(out of memory\?\)"),
        ("exit", "exited with code 3 without reporting"),
        ("Ctrl-C", "exited with code 1 without reporting"),
    ],
)
def test_a_worker_that_dies_is_reported_as_a_death_not_waited_for(how, reported):
    messages = []
    with pytest.raises(ShardError, match=rf"shard 1: its worker process \(pid \d+\) {reported}"):
        run_shards(count_or_die, [(False, how), (True, how)], lambda shard, m: messages.append((shard, m)))
    assert (1, "started") in messages, "its messages before the death arrive"


def count_or_die(dies: bool, how: str, progress) -> list[int]:
    return die(how, progress) if dies else count(0, 1, progress)


def test_the_workers_end_when_their_parent_is_killed(tmp_path):
    from tests.reliability.conftest import background, kill_parent_and_check_workers_end, wait_for

    script = (
        "import sys\n"
        "from mmf_rl.shards import run_shards\n"
        "from tests.test_shards import sleep_forever\n"
        "run_shards(sleep_forever, [(sys.argv[1],), (sys.argv[1],)])\n"
    )
    with background([sys.executable, "-c", script, str(tmp_path)]) as process:
        wait_for(lambda: len(list(tmp_path.glob("*.pid"))) == 2, process, 120, "two started workers")
        workers = [int(p.stem) for p in tmp_path.glob("*.pid")]
        kill_parent_and_check_workers_end(process, workers, "parent")
