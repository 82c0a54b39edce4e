"""Reading a LeRobot dataset for the window cache: memory that stays proportional to the columns read,
metadata opened once per state of meta/."""

import json
import os
import shutil
import tracemalloc
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from mmf_rl.datasets import lerobot_source
from mmf_rl.datasets.lerobot_source import load_frame_columns, open_dataset_metadata
from tests.datasets.conftest import SO101_ROOT

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


@pytest.fixture
def so101_copy(tmp_path, monkeypatch):
    """A writable copy of the so101 recording (its files keep their old mtimes), an empty metadata memo,
    and the list of the roots lerobot's ``LeRobotDatasetMetadata`` is constructed for."""
    from lerobot.datasets import lerobot_dataset

    root = Path(shutil.copytree(SO101_ROOT, tmp_path / "so101"))
    for path in root.rglob("*"):
        path.chmod(0o755 if path.is_dir() else 0o644)
    constructed = []

    class Counted(lerobot_dataset.LeRobotDatasetMetadata):
        def __init__(self, repo_id, root=None, **options):
            constructed.append(root)
            super().__init__(repo_id, root=root, **options)

    monkeypatch.setattr(lerobot_dataset, "LeRobotDatasetMetadata", Counted)
    lerobot_source._settled_metadata.cache_clear()
    yield SimpleNamespace(root=root, constructed=constructed)
    lerobot_source._settled_metadata.cache_clear()  # it holds this test's objects


def age(path: Path, seconds: float = 60) -> None:
    """Date ``path`` back ``seconds``: settled, the way a dataset recorded earlier is."""
    past = path.stat().st_mtime_ns - int(seconds * 1e9)
    os.utime(path, ns=(past, past))


def test_metadata_opened_again_is_not_read_again_and_no_caller_changes_the_next_ones(so101_copy):
    first = open_dataset_metadata(so101_copy.root, "so101")
    episodes, frames = first.total_episodes, first.total_frames
    first.info["total_frames"] = -1  # a caller changing its copy
    first.episodes = None
    second = open_dataset_metadata(str(so101_copy.root / ".." / "so101"), "so101")  # another spelling
    assert len(so101_copy.constructed) == 1
    assert second is not first and (second.total_episodes, second.total_frames) == (episodes, frames)
    assert second.root == so101_copy.root / ".." / "so101"  # the root as this caller gave it
    assert [int(e["episode_index"]) for e in second.episodes] == list(range(episodes))
    open_dataset_metadata(so101_copy.root, "other/repo")  # another repo_id is another entry
    assert len(so101_copy.constructed) == 2


def test_metadata_reloads_when_a_meta_file_changes(so101_copy):
    info_path = so101_copy.root / "meta" / "info.json"
    open_dataset_metadata(so101_copy.root, "so101")
    age(info_path)  # touched (same size and content, another mtime)
    open_dataset_metadata(so101_copy.root, "so101")
    open_dataset_metadata(so101_copy.root, "so101")
    assert len(so101_copy.constructed) == 2
    info = json.loads(info_path.read_text())
    info["fps"] = 7
    info_path.write_text(json.dumps(info, indent=4))  # rewritten just now
    assert open_dataset_metadata(so101_copy.root, "so101").fps == 7
    # A file written this instant could be rewritten within one timestamp tick, keeping size and
    # mtime: its fingerprint is not trusted until it has settled.
    assert open_dataset_metadata(so101_copy.root, "so101").fps == 7
    assert len(so101_copy.constructed) == 4
    age(info_path)
    open_dataset_metadata(so101_copy.root, "so101")
    assert open_dataset_metadata(so101_copy.root, "so101").fps == 7
    assert len(so101_copy.constructed) == 5


def test_broken_metadata_raises_each_time_and_its_restored_files_read_again(so101_copy):
    info_path = so101_copy.root / "meta" / "info.json"
    episodes_path = next((so101_copy.root / "meta" / "episodes").rglob("*.parquet"))
    open_dataset_metadata(so101_copy.root, "so101")
    info_path.write_text("{")
    for _ in range(2):
        with pytest.raises(ValueError, match=rf"{info_path}: not valid JSON"):
            open_dataset_metadata(so101_copy.root, "so101")
    shutil.copy2(SO101_ROOT / "meta" / "info.json", info_path)  # restored: the original size and mtime
    assert open_dataset_metadata(so101_copy.root, "so101").total_frames > 0
    assert len(so101_copy.constructed) == 1  # the state read first, from the memo
    # Its footer intact, a damaged page passes the file checks and fails inside lerobot: never stored.
    content = bytearray(episodes_path.read_bytes())
    content[100:2000] = bytes(b ^ 0x5A for b in content[100:2000])
    episodes_path.write_bytes(bytes(content))
    age(episodes_path)
    for _ in range(2):
        with pytest.raises(ValueError, match="could not read the dataset metadata"):
            open_dataset_metadata(so101_copy.root, "so101")
    assert len(so101_copy.constructed) == 3
