"""One dataset written in shards, one spawned process each, joined in order.

`mmf-rl record` and the ETH/UCY converter (`mmf_rl.datasets.ethucy`) spend their time in lerobot's
per-frame and per-episode writes, which one process cannot spread over the cores. So each worker
process writes a contiguous share into a LeRobot dataset of its own (a shard, `run_shards`), and
lerobot's `aggregate_datasets` concatenates the shards in order (`join_shards`): the dataset is
the same for any number of workers. Both write in a staging dir (`mmf_rl.temp_dirs.staging_dir`).

The workers are spawned, not forked: a fork copies the locks the parent's threads (torch,
logging) hold at that moment, held forever in the child, and state that does not survive it
(MuJoCo's GL contexts, torchcodec's decoders). Each runs one torch thread: the workers already
fill the cores, and torch's default of one thread per core in each would oversubscribe them.
Each ends when its parent ends, killed or not, so a killed run leaves no worker using a core for
a shard that nobody will join.
"""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import pickle
import signal
import threading
import traceback
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection, wait
from pathlib import Path

logger = logging.getLogger(__name__)

# How long a worker that reported its result, or whose reports ended, may take to exit.
EXIT_TIMEOUT_S = 5.0


class ShardError(RuntimeError):
    """A shard's worker raised or died. ``shard``: the shard's index; ``detail``: what happened, in
    one line; ``error``: the exception the worker raised, when it pickles (else None)."""

    def __init__(self, shard: int, detail: str, error: BaseException | None = None):
        super().__init__(f"shard {shard}: {detail}")
        self.shard, self.detail, self.error = shard, detail, error


def _exit_with_parent() -> None:
    """End this worker process when its parent ends (a thread waits on the parent's sentinel,
    which closes even when the parent is SIGKILLed and cannot stop its workers)."""
    parent = mp.parent_process()
    threading.Thread(target=lambda: (parent.join(), os._exit(1)), daemon=True).start()


def _picklable(error: BaseException) -> BaseException | None:
    """``error`` if the parent can rebuild it from its pickle, else None."""
    try:
        pickle.loads(pickle.dumps(error))
    except Exception:
        return None
    return error


def _run_shard(work: Callable, args: tuple, reports: Connection) -> None:
    """A worker process: ``work(*args, progress=...)``, every message and the outcome sent to the
    parent through ``reports`` (the pipe's only sending end: this process's exit closes it)."""
    _exit_with_parent()
    try:
        import torch

        torch.set_num_threads(1)
        result = work(*args, progress=lambda message: reports.send(("progress", message)))
        reports.send(("done", result))
    except KeyboardInterrupt:
        raise SystemExit(1) from None  # Ctrl-C reached the parent too, which stops the others
    except BaseException as error:
        detail = f"{type(error).__name__}: {error}"
        reports.send(("failed", (detail, _picklable(error), traceback.format_exc())))


def _death(shard: int, process) -> ShardError:
    """A worker whose reports ended without an outcome: what became of its process."""
    process.join(EXIT_TIMEOUT_S)
    code = process.exitcode
    if code is None:
        how = f"closed its reports but still runs after {EXIT_TIMEOUT_S:g} s"
    elif code == -signal.SIGKILL:
        how = "was killed by SIGKILL (out of memory?)"
    elif code < 0:
        how = f"was killed by signal {-code}"
    else:
        how = f"exited with code {code} without reporting"
    return ShardError(shard, f"its worker process (pid {process.pid}) {how}")


def _results(workers: list[tuple], on_progress: Callable[[int, object], None]) -> list:
    results = {}
    shard_of = {reports: k for k, (_, reports) in enumerate(workers)}
    while len(results) < len(workers):
        for reports in wait([r for r, k in shard_of.items() if k not in results]):
            k = shard_of[reports]
            try:
                kind, payload = reports.recv()
            except EOFError:  # every report sent before the exit is read first: none came
                raise _death(k, workers[k][0]) from None
            if kind == "progress":
                on_progress(k, payload)
            elif kind == "done":
                results[k] = payload
            else:
                detail, error, trace = payload
                logger.debug("shard %d's worker failed:\n%s", k, trace)
                raise ShardError(k, detail, error)
    return [results[k] for k in range(len(workers))]


def run_shards(
    work: Callable,
    shards: Sequence[tuple],
    on_progress: Callable[[int, object], None] = lambda shard, message: None,
) -> list:
    """``[work(*args, progress=...) for args in shards]``, each call in its own spawned process,
    started together; the results in order. ``progress(message)`` in shard ``k``'s process calls
    ``on_progress(k, message)`` here.

    The first shard whose ``work`` raises or whose process dies (killed, out of memory) stops the
    others and is raised as a `ShardError` naming it (the worker's traceback is logged at DEBUG);
    Ctrl-C stops them all. ``work`` must be importable by name (a module's function), and its
    arguments, messages and results picklable.
    """
    context = mp.get_context("spawn")
    workers = []
    finished = False
    try:
        for args in shards:
            reports, sender = context.Pipe(duplex=False)
            process = context.Process(target=_run_shard, args=(work, args, sender))
            process.start()
            sender.close()  # the worker's end lives in the worker only: its exit closes the pipe
            workers.append((process, reports))
        results = _results(workers, on_progress)
        finished = True
        return results
    finally:
        for process, reports in workers:
            if finished:  # it has reported, and may still be cleaning up on its way out
                process.join(EXIT_TIMEOUT_S)
            if process.is_alive():
                process.terminate()
            process.join()
            reports.close()


def join_shards(roots: Sequence[Path], root: Path, repo_id: str) -> None:
    """Make ``root`` the dataset of the shards' episodes in the order of ``roots``, renumbered from
    0, with lerobot's `aggregate_datasets` (statistics merged); a single shard is renamed."""
    if len(roots) == 1:
        os.rename(roots[0], root)
        return
    from lerobot.datasets.aggregate import aggregate_datasets

    aggregate_datasets(
        repo_ids=[repo_id] * len(roots), aggr_repo_id=repo_id, roots=list(roots), aggr_root=root
    )
