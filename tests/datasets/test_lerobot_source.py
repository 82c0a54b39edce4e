"""Reading a LeRobot dataset for the window cache: memory that stays proportional to the columns read."""

import shutil
import tracemalloc
from types import SimpleNamespace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from mmf_rl.datasets import lerobot_source
from mmf_rl.datasets.lerobot_source import load_frame_columns

FRAMES = 50_000
VECTORS = {"observation.state": 4, "observation.force": 3}
# Traced bytes while reading, per byte of the columns returned: the result, one column's reordering
# copy and arrow's buffers. Converting a list column through per-row arrays (an object per frame)
# costs several times more.
MAX_PEAK_PER_COLUMN_BYTE = 3


def write_frames(root, frames: int):
    """A data file as lerobot writes it (scalar and fixed-size list columns), rows out of frame order,
    and the metadata `load_frame_columns` reads."""
    order = np.random.default_rng(0).permutation(frames)
    columns = {
        "index": pa.array(order),
        "episode_index": pa.array(order // 250),
        "timestamp": pa.array((order % 250 / 25).astype(np.float32)),
    }
    for name, width in VECTORS.items():
        values = np.arange(frames * width, dtype=np.float32).reshape(frames, width)[order]
        columns[name] = pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()), width)
    (root / "data" / "chunk-000").mkdir(parents=True)
    pq.write_table(pa.table(columns), root / "data" / "chunk-000" / "file-000.parquet")
    features = {name: {"dtype": "int64", "shape": (1,)} for name in ("index", "episode_index")}
    features["timestamp"] = {"dtype": "float32", "shape": (1,)}
    features.update({name: {"dtype": "float32", "shape": (width,)} for name, width in VECTORS.items()})
    return SimpleNamespace(root=str(root), features=features, total_frames=frames)


def test_reading_columns_costs_a_few_times_their_size_and_orders_rows_by_frame_index(tmp_path):
    meta = write_frames(tmp_path / "dataset", FRAMES)
    wanted = ["episode_index", "timestamp", *VECTORS]
    load_frame_columns(meta, wanted)  # converts the parquet files to `datasets`' arrow cache once
    tracemalloc.start()
    try:
        data, _, _ = load_frame_columns(meta, wanted)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    returned = sum(column.nbytes for column in data.values())
    assert peak <= MAX_PEAK_PER_COLUMN_BYTE * returned, (
        f"reading {returned / 2**20:.1f} MiB of columns peaked at {peak / 2**20:.1f} MiB of traced memory"
    )
    assert np.array_equal(data["index"], np.arange(FRAMES))
    assert data["observation.state"].shape == (FRAMES, 4)
    assert np.array_equal(data["observation.force"][7], np.arange(21, 24, dtype=np.float32))


def test_a_decode_worker_keeps_the_decoder_of_one_video_file(synthetic_root, tmp_path):
    first = next((synthetic_root / "videos").rglob("*.mp4"))
    second = shutil.copy(first, tmp_path / "other.mp4")
    try:
        for path in (str(first), str(second), str(first)):
            lerobot_source._decoders(path).get_decoder(path)
            assert lerobot_source._decoder_cache.size() == 1
    finally:
        lerobot_source.clear_decoders()


@pytest.mark.parametrize("channels", [3, 1])
def test_an_episode_resized_in_one_call_per_size_stores_the_bytes_of_one_call_per_frame(channels):
    torch.manual_seed(0)
    size = (16, 32)
    shapes = [(20, 24), (16, 32), None, (20, 24), (40, 48), (16, 32), (20, 24)]  # None: undecodable
    frames = [None if s is None else torch.rand(channels, *s) for s in shapes]
    stored = lerobot_source._episode_cache_frames(frames, size, channels)
    one_by_one = [
        torch.zeros(channels, *size, dtype=torch.uint8)
        if f is None
        else lerobot_source.to_cache_frames(f[None], size, channels)[0]
        for f in frames
    ]
    assert stored.dtype == torch.uint8 and torch.equal(stored, torch.stack(one_by_one))
