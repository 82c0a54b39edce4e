"""A dataset from the hub is untrusted input: each defect is refused (or its episode skipped) by name.

Every check here runs on the metadata and the parquet footers, before the frames are read or the
cache allocated: paths escaping the root, absurd declared sizes, broken episode ranges. Defects
only the frames show are a warning and a skipped episode (timestamps going backwards) or an absent
camera (a video shorter than its parquet).
"""

import json
import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch

from mmf_rl.datasets import WindowDataset
from tests.reliability.conftest import edit_frames, push_data_config

CAMERA = "observation.images.front"


def edit_info(root, edit) -> None:
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    edit(info)
    path.write_text(json.dumps(info))


def edit_episodes(root, edit) -> None:
    [path] = (root / "meta" / "episodes").rglob("*.parquet")
    table = pq.read_table(path)
    episodes = table.to_pandas()
    edit(episodes)
    pq.write_table(pa.Table.from_pandas(episodes, schema=table.schema, preserve_index=False), path)


def open_dataset(root, cache_dir):
    return WindowDataset(push_data_config(root, cache_dir))


@pytest.mark.parametrize(
    "key, template",
    [
        ("video_path", "/etc/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"),
        ("video_path", "videos/../../../{video_key}/file-{file_index:03d}.mp4"),
        ("data_path", "../outside/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"),
    ],
)
def test_a_path_template_escaping_the_root_is_refused(push_copy, tmp_path, key, template):
    edit_info(push_copy, lambda info: info.__setitem__(key, template))
    with pytest.raises(ValueError, match=rf"meta/info.json: `{key}` .* leads outside the dataset root"):
        open_dataset(push_copy, tmp_path / "cache")
    assert not (tmp_path / "cache").exists(), "refused before any cache is written"


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda info: info.__setitem__("total_frames", 10**13),
            r"info.json: `total_frames` is 10000000000000, but the data files hold \d+ frames",
        ),
        (
            lambda info: info["features"][CAMERA].__setitem__("shape", [10**6, 10**6, 3]),
            rf"info.json: feature '{CAMERA}' declares `shape` \[1000000, 1000000, 3\], 3e\+12 values per "
            r"frame",
        ),
        (
            lambda info: info["features"]["observation.force"].__setitem__("shape", [10**12]),
            r"info.json: feature 'observation.force' declares `shape` \[1000000000000\]",
        ),
    ],
)
def test_absurd_declared_sizes_are_refused_before_any_allocation(push_copy, tmp_path, edit, message):
    # Allocating any of these would be terabytes (a MemoryError or an OOM kill, not this message).
    edit_info(push_copy, edit)
    with pytest.raises(ValueError, match=message):
        open_dataset(push_copy, tmp_path / "cache")


def shift_stop(episode: int, by: int):
    def edit(episodes):
        episodes.loc[episode, "dataset_to_index"] += by

    return edit


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda e: e.__setitem__("dataset_from_index", e["dataset_from_index"] - 100),
            r"episode 0 has dataset_from_index=-100, dataset_to_index=\d+; expected 0 <= from <= to <= \d+",
        ),
        (
            lambda e: e.__setitem__("dataset_to_index", e["dataset_from_index"] - 1),
            r"episode 0 has dataset_from_index=0, dataset_to_index=-1",
        ),
        (
            shift_stop(0, 5),
            r"episode 1 \(frames \d+\.\.\d+, dataset_from_index/dataset_to_index\) overlaps episode 0",
        ),
        (shift_stop(5, 5), r"episode 5 has .*expected 0 <= from <= to <= \d+"),
    ],
)
def test_negative_inverted_or_overlapping_episode_ranges_are_refused(push_copy, tmp_path, edit, message):
    edit_episodes(push_copy, edit)
    with pytest.raises(ValueError, match=r"meta/episodes/chunk-000/file-000.parquet: " + message):
        open_dataset(push_copy, tmp_path / "cache")


def test_timestamps_going_backwards_skip_the_episode_with_a_warning(push_copy, tmp_path):
    def rewind(frames):
        rows = np.flatnonzero(frames["episode_index"].to_numpy() == 2)
        frames.loc[rows[10], "timestamp"] = 0.0

    edit_frames(push_copy, rewind)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dataset = open_dataset(push_copy, tmp_path / "cache")
    messages = [str(w.message) for w in caught]
    assert any(
        "data/chunk-000/file-000.parquet: `timestamp` of episode 2 does not increase at frame 10" in m
        and "the episode is skipped" in m
        for m in messages
    ), messages
    assert 2 not in dataset.window_episode.tolist() and {0, 1, 3} <= set(dataset.window_episode.tolist())
    assert dataset.report["skipped"]["episodes_timestamps_not_increasing"] == [2]
    # Synced by frame index the stamps match no video frame: the episode is kept, its camera decoded.
    synced = WindowDataset(push_data_config(push_copy, tmp_path / "cache", video_sync="frame_index"))
    assert synced.report["skipped"]["episodes_timestamps_not_increasing"] == []
    assert synced.presence["image"][synced.window_episode == 2].all()


def test_a_video_shorter_than_its_parquet_makes_the_camera_absent_past_its_end(push_copy, tmp_path):
    import av

    [video] = (push_copy / "videos").rglob("*.mp4")
    episodes = pq.read_table(next((push_copy / "meta" / "episodes").rglob("*.parquet"))).to_pandas()
    cut_episode, kept_frames = 3, 20
    keep = int(episodes["dataset_from_index"][cut_episode]) + kept_frames  # the video ends inside episode 3
    shorter = video.with_name("shorter.mp4")
    with av.open(str(video)) as source, av.open(str(shorter), "w") as sink:
        stream = source.streams.video[0]
        out = sink.add_stream("mpeg4", rate=stream.average_rate)
        out.width, out.height, out.pix_fmt = stream.width, stream.height, "yuv420p"
        for index, frame in enumerate(source.decode(stream)):
            if index == keep:
                break
            sink.mux(out.encode(frame.reformat(format="yuv420p")))
        sink.mux(out.encode())
    shorter.replace(video)

    with pytest.warns(
        UserWarning,
        match=rf"{video.name} \(undecodable: the video has {keep} frames \([\d.]+ s\), "
        r"but the parquet rows of this episode need frames up to [\d.]+ s",
    ):
        dataset = open_dataset(push_copy, tmp_path / "cache")
    camera, episode = dataset.presence["image"], dataset.window_episode
    assert camera[episode < cut_episode].all() and not camera[episode > cut_episode].any()
    # In the cut episode, a window has the camera exactly when its observed frames are all in the video.
    history = 4
    first = dataset.window_start - int(episodes["dataset_from_index"][cut_episode])
    in_cut = episode == cut_episode
    assert torch.equal(camera[in_cut], first[in_cut] + history <= kept_frames)
    assert camera[in_cut].any() and not camera[in_cut].all()
    assert dataset.presence["force"].all(), "the other sensors of those episodes stay"
