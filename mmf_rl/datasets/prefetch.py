"""Batches one step ahead: gathered from the memory-mapped cache while the current step runs.

On CPU a background thread iterates the source (the gather from the memory map releases the GIL),
so the next batch is ready when the step ends. On CUDA the batch is also pinned and copied with
``non_blocking=True`` on a side stream; the consumer's stream waits on that copy only when it
takes the batch. The order is the source's own: prefetching changes when a batch is made, never
which batch comes next.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterable, Iterator

import torch
from tensordict import TensorDictBase

_END = object()
# How a loader makes a batch (its ``batch_making``), which decides where it may be made ahead:
# "thread_safe" (a gather: on a background thread), "global_rng" (its making draws from the global
# RNG, e.g. image augmentation on the training thread: only on the consumer's thread, which a
# second thread would interleave with the step's draws), "in_workers" (worker processes make most
# of it, e.g. image augmentation with `augment.workers`: a thread that mostly waits on them).
BATCH_MAKING = ("thread_safe", "global_rng", "in_workers")


class Prefetcher:
    """Iterate ``source`` (TensorDict batches) one batch ahead, moved to ``device``.

    ``threaded=False`` iterates the source on the caller's thread: required when making a batch
    draws from the global RNG (``"global_rng"`` of :data:`BATCH_MAKING`), which a second thread
    would interleave with the training step's draws. An exception raised by the
    source is raised by ``next``; :meth:`close` stops the thread (also at the end, or on
    ``with``-exit).
    """

    def __init__(self, source: Iterable[TensorDictBase], device: torch.device | str, threaded: bool = True):
        self.device = torch.device(device)
        self._source = iter(source)
        self._stream = torch.cuda.Stream(self.device) if self.device.type == "cuda" else None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        if threaded:
            self._thread = threading.Thread(target=self._work, name="mmf-rl-prefetch", daemon=True)
            self._thread.start()
        else:
            self._fetch_here()

    def _fetch(self):
        """The next batch on the device (with the event its copy records on CUDA), or ``_END``."""
        batch = next(self._source, _END)
        if batch is _END or self.device.type == "cpu":
            return batch
        if self._stream is None:
            return batch.to(self.device), None
        with torch.cuda.stream(self._stream):
            batch = batch.pin_memory().to(self.device, non_blocking=True)
            event = torch.cuda.Event()
            event.record(self._stream)
        return batch, event

    def _fetch_here(self) -> None:
        try:
            self._pending = self._fetch()
        except Exception as error:  # raised when its batch's turn comes, after the ones before it
            self._pending = error

    def _work(self) -> None:
        try:
            while not self._stop.is_set():
                item = self._fetch()
                self._put(item)
                if item is _END:
                    return
        except BaseException as error:  # handed to the consumer, raised there
            self._put(error)

    def _put(self, item) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def __iter__(self) -> Iterator[TensorDictBase]:
        return self

    def __next__(self) -> TensorDictBase:
        if self._stop.is_set():
            raise StopIteration
        if self._thread is None:
            item, self._pending = self._pending, _END
            if item is not _END and not isinstance(item, BaseException):
                self._fetch_here()
        else:
            item = self._queue.get()
        if isinstance(item, BaseException):
            self.close()
            raise item
        if item is _END:
            self.close()
            raise StopIteration
        return self._ready(item)

    def _ready(self, item) -> TensorDictBase:
        if self.device.type == "cpu":
            return item
        batch, event = item
        if event is not None:
            stream = torch.cuda.current_stream(self.device)
            stream.wait_event(event)
            # Memory made on the side stream is in use on this one: the allocator must know.
            batch.apply(lambda t: t.record_stream(stream))
        return batch

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            while self._thread.is_alive():
                try:  # unblock a worker waiting to put
                    self._queue.get_nowait()
                except queue.Empty:
                    self._thread.join(timeout=0.05)

    def __enter__(self) -> Prefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
