"""Building the window cache: what a build holds does not depend on how its work is split."""

import warnings

from tensordict import TensorDict

from mmf_rl.datasets import cache
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import synthetic_config

# Fewer windows than an episode has, so chunks end inside episodes.
SMALL_CHUNK = 7


def test_windows_checked_in_chunks_equal_windows_checked_at_once(synthetic_root, tmp_path, monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the synthetic dataset's absent spans
        whole = WindowDataset(synthetic_config(synthetic_root, tmp_path / "whole"))
        monkeypatch.setattr(cache, "WINDOW_CHUNK", SMALL_CHUNK)
        chunked = WindowDataset(synthetic_config(synthetic_root, tmp_path / "chunked"))
    assert chunked.built and len(chunked) > 2 * SMALL_CHUNK
    a, b = (TensorDict.load_memmap(d.cache_path / "windows") for d in (whole, chunked))
    assert (a == b).all()
    assert whole.report["skipped"] == chunked.report["skipped"]
