import threading

import pytest
import torch
from tensordict import TensorDict

from mmf_rl.datasets.prefetch import Prefetcher


def numbered(n: int, fail_at: int | None = None):
    for i in range(n):
        if i == fail_at:
            raise OSError(f"unreadable batch {i}")
        yield TensorDict({"x": torch.full((2, 3), float(i))}, batch_size=[2])


def prefetch_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "mmf-rl-prefetch"]


@pytest.mark.parametrize("threaded", [True, False])
def test_order_and_values_are_the_sources(threaded):
    batches = list(Prefetcher(numbered(7), "cpu", threaded=threaded))
    assert [int(b["x"][0, 0]) for b in batches] == list(range(7))
    assert all(b["x"].device.type == "cpu" for b in batches)
    assert not prefetch_threads()


def test_the_thread_runs_one_batch_ahead_and_stops_on_close():
    made = []

    def source():
        for batch in numbered(100):
            made.append(int(batch["x"][0, 0]))
            yield batch

    prefetcher = Prefetcher(source(), "cpu")
    assert int(next(prefetcher)["x"][0, 0]) == 0
    prefetcher.close()
    assert not prefetch_threads()
    assert len(made) <= 3  # the one taken, one queued, one waiting to be: never the whole source
    with pytest.raises(StopIteration):
        next(prefetcher)


@pytest.mark.parametrize("threaded", [True, False])
def test_an_error_of_the_source_is_raised_in_order_and_stops_the_thread(threaded):
    prefetcher = Prefetcher(numbered(10, fail_at=3), "cpu", threaded=threaded)
    assert [int(next(prefetcher)["x"][0, 0]) for _ in range(3)] == [0, 1, 2]
    with pytest.raises(OSError, match="unreadable batch 3"):
        next(prefetcher)
    assert not prefetch_threads()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="pinned memory and CUDA streams need a GPU")
def test_cuda_batches_arrive_on_the_device_in_order():
    batches = list(Prefetcher(numbered(5), "cuda"))
    assert [int(b["x"][0, 0]) for b in batches] == list(range(5))
    assert all(b["x"].device.type == "cuda" for b in batches)
