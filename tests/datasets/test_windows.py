"""Reading windows from the cache: the image columns' mapping."""

import warnings

import pytest
import torch
from tensordict import MemoryMappedTensor, TensorDict

from mmf_rl.datasets import windows
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import synthetic_config

BATCHES, BATCH = 6, 8


def test_batches_read_through_fresh_mappings_equal_those_read_through_one(
    synthetic_root, tmp_path, monkeypatch
):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the synthetic dataset's absent spans
        data = WindowDataset(synthetic_config(synthetic_root, tmp_path / "cache"))
    mapped = []
    map_images = WindowDataset._map_images
    monkeypatch.setattr(WindowDataset, "_map_images", lambda self: mapped.append(map_images(self)))
    ids = torch.arange(BATCHES * BATCH).split(BATCH)
    once = [data.batch(i) for i in ids]
    assert not mapped, "an image table smaller than REMAP_IMAGE_BYTES is mapped once"
    monkeypatch.setattr(windows, "REMAP_IMAGE_BYTES", 0)
    fresh = [data.batch(i) for i in ids]
    assert len(mapped) == BATCHES, "each batch read some image bytes, so the next one maps afresh"
    for a, b in zip(once, fresh, strict=True):
        assert (a == b).all()


def test_a_fresh_mapping_maps_the_image_columns_alone(synthetic_root, tmp_path, monkeypatch):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the synthetic dataset's absent spans
        data = WindowDataset(synthetic_config(synthetic_root, tmp_path / "cache"))
    files = []
    from_filename = MemoryMappedTensor.from_filename
    monkeypatch.setattr(
        MemoryMappedTensor,
        "from_filename",
        lambda filename, *args, **kwargs: files.append(filename) or from_filename(filename, *args, **kwargs),
    )
    monkeypatch.setattr(
        TensorDict, "load_memmap", lambda *args: pytest.fail(f"batch mapped a whole table again: {args}")
    )
    monkeypatch.setattr(windows, "REMAP_IMAGE_BYTES", 0)
    for ids in torch.arange(2 * BATCH).split(BATCH):
        data.batch(ids)
    assert len(files) == 1 and files[0].startswith(str(data.cache_path)) and files[0].endswith("image.memmap")
