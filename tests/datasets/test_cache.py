"""Building the window cache: what a build holds does not depend on how its work is split."""

import warnings
from concurrent.futures import ProcessPoolExecutor

import pytest
from tensordict import TensorDict

from mmf_rl.datasets import cache
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import camera_config, differing_files, synthetic_config

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


@pytest.mark.slow
def test_images_decoded_by_two_processes_build_the_cache_of_one(broken_images_root, tmp_path, monkeypatch):
    """Two processes with four jobs per camera, or one process with one job per camera: the same frame
    table (resized, undecodable images absent) and the same report, byte for byte."""
    pools = []

    class RecordedPool(ProcessPoolExecutor):
        def __init__(self, max_workers, **kwargs):
            pools.append(max_workers)
            super().__init__(max_workers, **kwargs)

    monkeypatch.setattr(cache, "ProcessPoolExecutor", RecordedPool)
    config = {"image_size": [8, 12]}  # resized: frames are interpolated together
    with pytest.warns(UserWarning, match="undecodable"):
        pooled = WindowDataset(
            camera_config(broken_images_root, tmp_path / "pooled", **config), num_workers=2
        )
    assert pools == [2]
    monkeypatch.setattr(cache, "IMAGE_JOBS_PER_WORKER", 1)
    with pytest.warns(UserWarning, match="undecodable"):
        single = WindowDataset(
            camera_config(broken_images_root, tmp_path / "single", **config), num_workers=1
        )
    assert pools == [2], "the one-process build ran in this process"

    assert pooled.report == single.report and pooled.report["undecodable_files"]["wrist"]
    assert differing_files(single.cache_path, pooled.cache_path) == []
