"""Reading windows from the cache: the image columns' mapping, the warning on missing files."""

import logging
import warnings

import pytest
import torch
from tensordict import MemoryMappedTensor, TensorDict

from mmf_rl.datasets import windows
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import (
    UNCONVENTIONAL_CAMERA,
    UNCONVENTIONAL_EPISODES,
    UNCONVENTIONAL_STATE,
    synthetic_config,
)

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


def test_the_warning_on_missing_video_files_shows_a_count_the_first_few_and_where_the_rest_are(
    unconventional_root, tmp_path, caplog
):
    """Every video file missing (they sit under video/, not videos/): a count, the first files, and
    where the full list is, in a few lines; the whole list at debug level."""
    config = DataConfig.from_dict(
        {
            "root": str(unconventional_root),
            "cache_dir": str(tmp_path),
            "history": 3,
            "horizon": 2,
            "image_size": [16, 32],
            "modalities": {
                "camera": {"feature": UNCONVENTIONAL_CAMERA, "allow_absent": True},
                "state": UNCONVENTIONAL_STATE,
            },
            "target": {"feature": UNCONVENTIONAL_STATE},
        }
    )
    with caplog.at_level(logging.DEBUG, logger="mmf_rl"), pytest.warns(UserWarning) as caught:
        dataset = WindowDataset(config)
    (warning,) = [str(w.message) for w in caught if "marked present=False" in str(w.message)]
    count = len(UNCONVENTIONAL_EPISODES)
    assert len(warning.splitlines()) == 2 and len(warning) < 800
    first = ", ".join(f"videos/image/chunk-000/file-00{i}.mp4 (missing)" for i in range(3))
    assert f"'camera' ({UNCONVENTIONAL_CAMERA}): {count} file(s): {first} and {count - 3} more" in warning
    assert f"The full list is in {dataset.cache_path / 'cache.json'} (`missing_files`" in warning
    assert f"`mmf-rl inspect {unconventional_root}`" in warning
    assert len(dataset.report["missing_files"]["camera"]) == count
    (logged,) = [
        r.getMessage() for r in caplog.records if "every missing or undecodable file" in r.getMessage()
    ]
    assert all(p in logged for p in dataset.report["missing_files"]["camera"])
