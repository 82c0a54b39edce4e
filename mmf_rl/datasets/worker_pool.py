"""Worker processes that apply one function to a stream of requests, answering in request order.

Used to take image augmentation off the training thread (:mod:`mmf_rl.datasets.augment`). The
processes are spawned, not forked: the trainer forks from a process whose torch thread pool and
prefetch thread are running, and a fork copies the locks those threads may hold at that moment
(held forever in the child) and an OpenMP pool that is not valid there. A spawned worker starts
clean, at the price of importing torch once per pool.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from multiprocessing.connection import wait
from typing import NoReturn

import torch
import torch.multiprocessing as torch_mp

# How long a closed worker may take to finish the request it is on before it is terminated.
CLOSE_TIMEOUT_S = 5.0


def _serve(connection, make: Callable[[], Callable], threads: int) -> None:
    """A worker's loop: ``make()`` once, then answer each ``(ticket, args)`` with its result."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's: it closes the pool
    torch.set_num_threads(threads)
    function = make()
    while True:
        try:
            ticket, args = connection.recv()
        except (EOFError, ConnectionError):  # the pool was closed, or the parent died (its end closed)
            return
        try:
            answer = (ticket, True, function(*args))
        except Exception as error:  # raised in the parent, when its request's result is taken
            answer = (ticket, False, error)
        try:
            connection.send(answer)
        except ConnectionError:  # closed while this request ran
            return


class WorkerPool:
    """``count`` spawned processes, each running ``make()`` once and then the function it returns
    on every request it is sent.

    Requests go round-robin and each process answers its own in turn, so :meth:`result` returns
    results in the order :meth:`submit` took them, whatever the count. Tensors travel in shared
    memory (``torch.multiprocessing``'s pickling): only their handles go through the pipes. A
    result never taken (its consumer stopped early) is skipped when a later one is read.

    Each process runs ``threads`` intra-op threads (default one): the workers share the cores with
    the process that feeds them, and giving each as many threads as it has oversubscribes them.

    A process that dies is an error naming ``role``, its exit code and ``fix``, raised by the call
    waiting on it, never a wait forever; the pool then closes. Each process holds only its own
    end of a pipe, so it sees the pipe close and exits when the pool is closed or its parent dies,
    killed or not (``concurrent.futures``' process pool leaves its workers blocked on a queue they
    also hold open, when the parent is killed).
    """

    def __init__(self, make: Callable[[], Callable], count: int, role: str, fix: str, threads: int = 1):
        if count < 1:
            raise ValueError(f"a worker pool needs at least one process, found count={count}")
        self.role, self.fix = role, fix
        context = torch_mp.get_context("spawn")
        self._workers = []
        for i in range(count):
            parent_end, child_end = context.Pipe()
            process = context.Process(
                target=_serve,
                args=(child_end, make, threads),
                name=f"mmf-rl-{role.replace(' ', '-')}-{i}",
                daemon=True,
            )
            process.start()
            child_end.close()  # the child's end lives in the child only: its exit closes the pipe
            self._workers.append((process, parent_end))
        self._next_ticket = 0
        self.closed = False

    def submit(self, *args) -> int:
        """Send ``args`` to the next process; the ticket to :meth:`result` for."""
        ticket = self._next_ticket
        self._next_ticket += 1
        process, connection = self._worker(ticket)
        try:
            connection.send((ticket, args))
        except ConnectionError:
            self._died(process)
        return ticket

    def result(self, ticket: int):
        """The result of request ``ticket`` (raised, if it raised), waiting for it."""
        process, connection = self._worker(ticket)
        while True:
            if connection not in wait([connection, process.sentinel]):
                self._died(process)
            try:
                answered, ok, value = connection.recv()
            except (EOFError, ConnectionError):  # died while answering
                self._died(process)
            if answered == ticket:
                break
        if not ok:
            raise value
        return value

    def _worker(self, ticket: int):
        if self.closed:
            raise RuntimeError(f"the {self.role} worker pool is closed")
        return self._workers[ticket % len(self._workers)]

    def _died(self, process) -> NoReturn:
        process.join(CLOSE_TIMEOUT_S)
        code = process.exitcode
        how = f"was killed by signal {-code}" if code is not None and code < 0 else f"exited with code {code}"
        self.close()
        raise RuntimeError(f"the {self.role} worker process (pid {process.pid}) {how}; {self.fix}")

    def close(self) -> None:
        """Stop the processes: each finishes the request it is on (terminated after
        ``CLOSE_TIMEOUT_S``); results not taken are dropped."""
        if self.closed:
            return
        self.closed = True
        for _, connection in self._workers:
            connection.close()
        for process, _ in self._workers:
            process.join(CLOSE_TIMEOUT_S)
            if process.is_alive():
                process.terminate()
                process.join()
