"""The LeRobot → windows pipeline: reading, presence, windows, splits, cache, loaders."""

import hashlib
import os
import re
import warnings
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from safetensors.torch import load_file, save_file
from tensordict import TensorDict

from benchmarks.synthetic.dataset import FORCE_FEATURE, IMAGE_FEATURE, POSE_FEATURE, STATE_FEATURE
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.datasets.windows import WindowDataset
from mmf_rl.keys import (
    FUTURE_ACTION,
    TARGET,
    TARGET_PAST,
    obs_key,
    present_key,
    present_steps_key,
    validate_batch,
)
from tests.datasets.conftest import (
    EPISODE_LENGTHS,
    INVALID_IMAGE_EPISODE,
    NAN_FORCE_EPISODE,
    SO101_ROOT,
    needs_so101,
    record_synthetic,
    so101_config,
    synthetic_config,
)
from tests.reliability.conftest import push_data_config


def raw_frames(root) -> pd.DataFrame:
    frames = pd.concat([pd.read_parquet(p) for p in sorted((root / "data").glob("*/*.parquet"))])
    return frames.sort_values("index").reset_index(drop=True)


def column(frames: pd.DataFrame, feature: str) -> np.ndarray:
    return np.stack(frames[feature].to_numpy()).astype(np.float32)


def open_quietly(config, **kwargs) -> WindowDataset:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WindowDataset(config, **kwargs)


def all_windows(dataset: WindowDataset):
    return dataset.batch(torch.arange(len(dataset)))


# --- the real SO-101 recording: cameras declared, videos absent -------------------------------


@needs_so101
def test_so101_loads_with_cameras_absent_and_warns_naming_files(tmp_path):
    before = {p: p.stat().st_mtime_ns for p in SO101_ROOT.rglob("*")}
    with pytest.warns(UserWarning) as record:
        dataset = WindowDataset(so101_config(tmp_path))
    message = " ".join(str(w.message) for w in record)
    for camera in ("observation.images.front", "observation.images.top"):
        assert f"videos/{camera}/chunk-000/file-000.mp4" in message
    assert not dataset.presence["front"].any() and not dataset.presence["top"].any()
    assert dataset.presence["state"].all()
    # 4 episodes, 1,492 frames; each episode of n frames has n - (H + T - 1) windows.
    assert len(dataset) == 1492 - 4 * 9
    batch = next(iter(dataset.loader("train", batch_size=16)))
    validate_batch(batch, dataset.specs, history=5, horizon=5, target_dim=3, require_target=True)
    assert not batch.get(present_key("front")).any()
    assert {p: p.stat().st_mtime_ns for p in SO101_ROOT.rglob("*")} == before, "the fixture was written to"


@needs_so101
def test_so101_required_camera_is_a_clear_error(tmp_path):
    config = so101_config(tmp_path)
    config.modalities["front"].required = True
    with pytest.raises(
        FileNotFoundError, match=r"required modality.*'front'.*observation\.images\.front.*file-000\.mp4"
    ):
        WindowDataset(config)


@needs_so101
def test_so101_camera_absent_on_every_frame_is_an_error_unless_accepted(tmp_path):
    config = so101_config(tmp_path)
    config.modalities["top"].allow_absent = False
    with pytest.raises(
        ValueError,
        match=r"modality 'top' \(observation\.images\.top\) is absent on 100\.0% of the 1492 frames.*"
        r"video file\(s\) missing.*file-000\.mp4.*Restore the video files, or accept it with "
        r"data\.modalities\.top\.allow_absent=true",
    ):
        WindowDataset(config)


def test_bad_feature_name_lists_available_features(synthetic_root, tmp_path):
    config = synthetic_config(synthetic_root, tmp_path, modalities={"state": "observation.stat"})
    with pytest.raises(ValueError, match=r"'observation\.stat' is not in the dataset.*'observation\.state'"):
        WindowDataset(config)
    with pytest.raises(ValueError, match=r"target.*'nope'.*available features"):
        WindowDataset(synthetic_config(synthetic_root, tmp_path, target="nope"))
    with pytest.raises(FileNotFoundError, match=r"not a LeRobot dataset.*meta/info\.json"):
        WindowDataset(synthetic_config(tmp_path, tmp_path))
    bad_validity = {"state": {"feature": STATE_FEATURE, "valid_feature": "observation.state_ok"}}
    with pytest.raises(ValueError, match=r"valid_feature.*'observation\.state_ok' is not in the dataset"):
        WindowDataset(synthetic_config(synthetic_root, tmp_path, modalities=bad_validity))
    with pytest.raises(ValueError, match=r"dims \[4\] out of range.*width 4"):
        WindowDataset(
            synthetic_config(synthetic_root, tmp_path, target={"feature": STATE_FEATURE, "dims": [4]})
        )


@needs_so101
@pytest.mark.parametrize("stride", [1, 2])
def test_so101_action_windows_are_the_commands_over_the_horizon(tmp_path, stride):
    """A world model's ``future_action`` on the real SO-101 recording: the actions of frames
    t .. t + T*stride - 1 (t = last observed frame), normalised with training-split statistics."""
    history, horizon = 5, 5
    dataset = open_quietly(so101_config(tmp_path, stride=stride, action="action"))
    assert dataset.action_shape == (horizon * stride, 6)
    batch = all_windows(dataset)
    validate_batch(
        batch,
        dataset.specs,
        history,
        horizon,
        target_dim=3,
        require_target=True,
        action_shape=dataset.action_shape,
    )
    actions = torch.from_numpy(column(raw_frames(SO101_ROOT), "action"))
    stats = dataset.normalizer.stats
    t = dataset.window_start + (history - 1) * stride
    expected = actions[t[:, None] + torch.arange(horizon * stride)]
    torch.testing.assert_close(
        batch.get(FUTURE_ACTION) * stats["future_action/std"] + stats["future_action/mean"],
        expected,
        rtol=1e-5,
        atol=1e-4,
    )
    train_frames = torch.isin(
        torch.tensor(raw_frames(SO101_ROOT)["episode_index"].to_numpy()),
        torch.tensor(dataset.split_episodes["train"]),
    )
    torch.testing.assert_close(
        stats["future_action/mean"], actions[train_frames].mean(0), rtol=1e-4, atol=1e-4
    )
    # Without `action` the same frames serve a plain forecaster: no action key, and its own cache.
    plain = open_quietly(so101_config(tmp_path, stride=stride))
    assert plain.action_shape is None and FUTURE_ACTION not in plain.batch(torch.arange(4)).keys()
    assert plain.cache_path != dataset.cache_path


def test_action_feature_errors_name_the_feature(synthetic_root, tmp_path):
    with pytest.raises(
        ValueError, match=r"action: feature 'act' is not in the dataset.*'observation\.state'"
    ):
        WindowDataset(synthetic_config(synthetic_root, tmp_path, action="act"))
    with pytest.raises(
        ValueError, match=r"action: feature 'observation\.images\.front' has dtype 'video'.*numeric vector"
    ):
        WindowDataset(synthetic_config(synthetic_root, tmp_path, action="observation.images.front"))
    with pytest.raises(ValueError, match=r"dims \[9\] out of range"):
        WindowDataset(
            synthetic_config(synthetic_root, tmp_path, action={"feature": STATE_FEATURE, "dims": [9]})
        )
    with pytest.raises(ValueError, match=r"unknown key.*featur"):
        synthetic_config(synthetic_root, tmp_path, action={"featur": STATE_FEATURE})


def test_config_from_dict_round_trip_and_errors():
    d = {
        "root": "/data",
        "modalities": {
            "image": "observation.images.front",
            "force": {"feature": "observation.force", "required": True},
        },
        "target": {"feature": "observation.object_pose", "dims": [0, 1]},
        "stride": 2,
        "missing": {"force": 0.25},
        "missing_seed": 7,
    }
    config = DataConfig.from_dict(d)
    assert config.modalities["image"].feature == "observation.images.front"
    assert config.modalities["force"].required and config.stride == 2
    assert DataConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown key.*histroy"):
        DataConfig.from_dict({**d, "histroy": 3})
    with pytest.raises(ValueError, match="`missing` names modality 'camera'"):
        DataConfig.from_dict({**d, "missing": {"camera": 0.5}})
    with pytest.raises(ValueError, match="split_fractions"):
        DataConfig.from_dict({**d, "split_fractions": [0.5, 0.5, 0.5]})


# --- the synthetic dataset: video, NaN spans, validity feature ---------------------------------


@pytest.mark.parametrize("stride", [1, 2])
def test_windows_match_raw_parquet_and_stay_in_episodes(synthetic_root, tmp_path, stride):
    history, horizon = 4, 3
    dataset = open_quietly(
        synthetic_config(synthetic_root, tmp_path, stride=stride, include_target_past=True)
    )
    frames = raw_frames(synthetic_root)
    pose, state = column(frames, POSE_FEATURE)[:, :2], column(frames, STATE_FEATURE)
    span = (history + horizon - 1) * stride

    expected = sum(max(0, n - span) for n in EPISODE_LENGTHS)
    assert len(dataset) == expected
    assert dataset.report["skipped"]["episodes_too_short"] == [
        i for i, n in enumerate(EPISODE_LENGTHS) if n <= span
    ]

    batch = all_windows(dataset)
    validate_batch(batch, dataset.specs, history, horizon, target_dim=2, require_target=True)
    target = dataset.normalizer.denormalize_target(batch.get(TARGET))
    t = dataset.window_start + (history - 1) * stride  # the last observed frame
    future = t[:, None] + torch.arange(1, horizon + 1) * stride
    torch.testing.assert_close(target, torch.from_numpy(pose)[future])
    past = dataset.normalizer.denormalize_target(batch.get(TARGET_PAST))
    observed = t[:, None] - torch.arange(history - 1, -1, -1) * stride
    torch.testing.assert_close(past, torch.from_numpy(pose)[observed])
    state_obs = (
        batch.get(obs_key("state")) * dataset.normalizer.stats["state/std"]
        + dataset.normalizer.stats["state/mean"]
    )
    torch.testing.assert_close(state_obs, torch.from_numpy(state)[observed], rtol=1e-5, atol=1e-4)
    # pose[0] = episode + frame / 1000: every observed and future frame of a window is one episode.
    episode_of = torch.floor(torch.cat([past[..., 0], target[..., 0]], 1) + 1e-4)
    assert (episode_of == dataset.window_episode[:, None].float()).all()


def test_relative_target_is_the_change_from_the_last_observed_frame(synthetic_root, tmp_path):
    absolute = open_quietly(synthetic_config(synthetic_root, tmp_path, include_target_past=True))
    relative = open_quietly(
        synthetic_config(
            synthetic_root,
            tmp_path,
            include_target_past=True,
            target={"feature": POSE_FEATURE, "dims": [0, 1], "relative": True},
        )
    )
    assert relative.cache_path == absolute.cache_path  # same frames: the cache is shared
    ids = torch.arange(len(absolute))
    a, r = absolute.batch(ids), relative.batch(ids)
    future_abs = absolute.normalizer.denormalize_target(a.get(TARGET))
    past_abs = absolute.normalizer.denormalize_target(a.get(TARGET_PAST))
    anchor = past_abs[:, -1:]
    torch.testing.assert_close(relative.normalizer.denormalize_target(r.get(TARGET)), future_abs - anchor)
    past_rel = relative.normalizer.denormalize_target(r.get(TARGET_PAST))
    torch.testing.assert_close(past_rel, past_abs - anchor)
    assert past_rel[:, -1].abs().max() < 1e-5
    # Statistics describe the training windows' displacements, not positions.
    train = relative.split_windows["train"]
    displacement = (future_abs - anchor)[train].reshape(-1, 2)
    torch.testing.assert_close(
        relative.normalizer.stats["target/mean"], displacement.mean(0), rtol=1e-4, atol=1e-6
    )
    torch.testing.assert_close(
        relative.normalizer.stats["target/std"],
        displacement.std(0, correction=0).clamp_min(1e-3),
        rtol=1e-4,
        atol=1e-6,
    )


def test_presence_masks_follow_nan_spans_and_validity(synthetic_root, tmp_path):
    dataset = open_quietly(synthetic_config(synthetic_root, tmp_path))
    frames = raw_frames(synthetic_root)
    frame_index = torch.tensor(frames["frame_index"].to_numpy())
    observed = dataset.window_start[:, None] + torch.arange(4)
    touches_span = ((frame_index[observed] >= 5) & (frame_index[observed] < 10)).any(1)
    episode = dataset.window_episode
    assert torch.equal(dataset.presence["force"], ~(touches_span & (episode == NAN_FORCE_EPISODE)))
    assert torch.equal(dataset.presence["image"], ~(touches_span & (episode == INVALID_IMAGE_EPISODE)))
    assert dataset.presence["state"].all()
    assert (~dataset.presence["force"]).sum() > 0 and (~dataset.presence["image"]).sum() > 0

    batch = all_windows(dataset)
    force = batch.get(obs_key("force"))
    assert torch.isfinite(force).all()
    assert (force[~batch.get(present_key("force"))] == 0).all()
    raw_force = column(frames, FORCE_FEATURE)
    assert np.isnan(raw_force).any(), "the fixture should contain NaN force values"
    image = batch.get(obs_key("image"))
    assert image.dtype == torch.uint8 and image.shape[-3:] == (3, 24, 24) and image.float().mean() > 1


def test_missing_and_undecodable_videos_mark_camera_absent(synthetic_copy, tmp_path):
    video = next((synthetic_copy / "videos").rglob("*.mp4"))
    video.write_bytes(b"not an mp4 file")
    # The one video holds every episode: the camera is lost on every frame, an error unless accepted.
    with pytest.raises(
        ValueError, match=rf"'image'.*absent on 100\.0%.*undecodable.*{video.name}.*allow_absent=true"
    ):
        WindowDataset(synthetic_config(synthetic_copy, tmp_path / "a"))
    accepted = {
        "image": {"feature": IMAGE_FEATURE, "allow_absent": True},
        "state": STATE_FEATURE,
        "force": FORCE_FEATURE,
    }
    with pytest.warns(UserWarning, match=rf"{video.name} \(undecodable"):
        dataset = WindowDataset(synthetic_config(synthetic_copy, tmp_path / "a", modalities=accepted))
    assert not dataset.presence["image"].any() and dataset.presence["state"].all()

    video.unlink()  # declared in meta/info.json, missing on disk
    with pytest.warns(UserWarning, match=rf"{video.name} \(missing\)"):
        dataset = WindowDataset(synthetic_config(synthetic_copy, tmp_path / "b", modalities=accepted))
    assert not dataset.presence["image"].any()
    validate_batch(all_windows(dataset), dataset.specs, 4, 3, 2)
    required = synthetic_config(synthetic_copy, tmp_path / "b")
    required.modalities["image"].required = True
    with pytest.raises(
        FileNotFoundError, match=rf"required modality.*'image'.*observation\.images\.front.*{video.name}"
    ):
        WindowDataset(required)


def test_split_by_episode_and_stats_from_train_only(synthetic_root, tmp_path):
    dataset = open_quietly(synthetic_config(synthetic_root, tmp_path, split_seed=3))
    splits = dataset.split_episodes
    assert sorted(splits["train"] + splits["val"] + splits["test"]) == list(range(len(EPISODE_LENGTHS)))
    assert all(splits[name] for name in splits)
    for name, ids in dataset.split_windows.items():
        assert set(dataset.window_episode[ids].tolist()) <= set(splits[name])
    assert sum(len(ids) for ids in dataset.split_windows.values()) == len(dataset)
    assert open_quietly(synthetic_config(synthetic_root, tmp_path, split_seed=3)).split_episodes == splits

    frames = raw_frames(synthetic_root)
    train = frames["episode_index"].isin(splits["train"]).to_numpy()
    force = column(frames, FORCE_FEATURE)[train]
    force = force[np.isfinite(force).all(1)]
    stats = dataset.normalizer.stats
    torch.testing.assert_close(stats["force/mean"], torch.from_numpy(force.mean(0)), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(stats["force/std"], torch.from_numpy(force.std(0)), atol=1e-5, rtol=1e-5)
    pose = column(frames, POSE_FEATURE)[train][:, :2]
    torch.testing.assert_close(stats["target/mean"], torch.from_numpy(pose.mean(0)), atol=1e-5, rtol=1e-5)
    all_pose = column(frames, POSE_FEATURE)[:, :2]
    assert not np.allclose(all_pose.mean(0), pose.mean(0)), "train-only stats must differ from all-data stats"

    save_file(stats, tmp_path / "stats.safetensors")  # stored with a run, restored for metrics
    restored = Normalizer(load_file(tmp_path / "stats.safetensors"))
    target = dataset.batch(dataset.split_windows["test"]).get(TARGET)
    torch.testing.assert_close(
        restored.denormalize_target(target), dataset.normalizer.denormalize_target(target)
    )


def test_constant_dims_get_the_std_floor(synthetic_root, tmp_path):
    # state[2:4] is the per-episode velocity: constant within an episode, so with a single
    # training episode its std is 0 and must be floored.
    config = synthetic_config(synthetic_root, tmp_path, split_fractions=[0.2, 0.4, 0.4], std_floor=0.01)
    dataset = open_quietly(config)
    assert len(dataset.split_episodes["train"]) == 1
    assert torch.equal(dataset.normalizer.stats["state/std"][2:], torch.full((2,), 0.01))
    assert torch.isfinite(all_windows(dataset).get(obs_key("state"))).all()


def test_cache_reused_when_unchanged_rebuilt_when_files_or_config_change(synthetic_copy, tmp_path):
    config = synthetic_config(synthetic_copy, tmp_path)
    first = open_quietly(config)
    assert first.built
    second = open_quietly(config)
    assert not second.built and second.cache_path == first.cache_path
    torch.testing.assert_close(all_windows(first), all_windows(second))

    changed_config = open_quietly(synthetic_config(synthetic_copy, tmp_path, horizon=2))
    assert changed_config.built and changed_config.cache_path != first.cache_path
    # Split and protocol settings do not change the cached content.
    assert not open_quietly(synthetic_config(synthetic_copy, tmp_path, split_seed=9)).built

    data_file = next((synthetic_copy / "data").rglob("*.parquet"))
    stat = data_file.stat()
    os.utime(data_file, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    touched = open_quietly(config)
    assert touched.built and touched.cache_path not in (first.cache_path, changed_config.cache_path)


def test_killed_build_never_reads_as_a_cache(synthetic_root, tmp_path, monkeypatch):
    import mmf_rl.datasets.cache as cache

    def crash(*args, **kwargs):
        raise KeyboardInterrupt("simulated kill during the build")

    monkeypatch.setattr(cache, "_windows", crash)
    config = synthetic_config(synthetic_root, tmp_path)
    with pytest.raises(KeyboardInterrupt):
        open_quietly(config)
    assert list(tmp_path.iterdir()) == []  # neither a cache nor a half-written temp dir
    monkeypatch.undo()
    assert open_quietly(config).built


@pytest.mark.slow
def test_pool_build_equals_in_process_build(synthetic_root, tmp_path):
    in_process = open_quietly(synthetic_config(synthetic_root, tmp_path / "a"), num_workers=1)
    pooled = open_quietly(synthetic_config(synthetic_root, tmp_path / "b"), num_workers=2)
    assert pooled.built and in_process.built
    torch.testing.assert_close(all_windows(pooled), all_windows(in_process))


@pytest.fixture
def one_encoding_per_episode(monkeypatch) -> Counter:
    """Recordings made with this fixture share one bitstream per episode's frames; returns how many
    times each bitstream was used.

    lerobot encodes each episode apart (libx264 here) before it moves or stream-copies the result into
    a video file. The encoder's output also depends on uninitialised memory, so two encodings of the
    same frames may differ by a few grey levels: two layouts compared pixel for pixel must hold the
    same encoded frames.
    """
    from lerobot.datasets import lerobot_dataset

    encode = lerobot_dataset.encode_video_frames
    bitstreams: dict[str, bytes] = {}
    uses: Counter = Counter()

    def encode_once(imgs_dir, video_path, *args, **kwargs) -> None:
        frames = hashlib.sha256()
        for png in sorted(Path(imgs_dir).glob("frame-*.png")):
            frames.update(png.read_bytes())
        key = frames.hexdigest()
        if key not in bitstreams:
            encode(imgs_dir, video_path, *args, **kwargs)
            bitstreams[key] = Path(video_path).read_bytes()
        else:
            Path(video_path).write_bytes(bitstreams[key])
        uses[key] += 1

    monkeypatch.setattr(lerobot_dataset, "encode_video_frames", encode_once)
    return uses


def test_video_split_over_many_files_reads_like_one_file(one_encoding_per_episode, tmp_path):
    # lerobot starts a new video file once the current one would pass video_files_size_in_mb; a
    # 1 KB cap puts every episode in its own file (the layout of large datasets).
    one_file = record_synthetic(tmp_path / "one_file")
    many_files = record_synthetic(tmp_path / "many_files", video_files_size_in_mb=0.001)
    assert list(one_encoding_per_episode.values()) == [2] * len(EPISODE_LENGTHS), "an episode encoded twice"
    assert len(list((many_files / "videos").rglob("*.mp4"))) == len(EPISODE_LENGTHS)
    assert len(list((one_file / "videos").rglob("*.mp4"))) == 1
    split = open_quietly(synthetic_config(many_files, tmp_path / "a"))
    single = open_quietly(synthetic_config(one_file, tmp_path / "b"))
    torch.testing.assert_close(all_windows(split), all_windows(single))


# --- loaders -----------------------------------------------------------------------------------


def test_loader_shuffles_reproducibly_and_shards_by_rank(synthetic_root, tmp_path):
    dataset = open_quietly(synthetic_config(synthetic_root, tmp_path))
    train = dataset.split_windows["train"]

    def epoch_targets(loader):
        return torch.cat([b.get(TARGET) for b in loader])

    a, b = dataset.loader("train", 8, seed=1), dataset.loader("train", 8, seed=1)
    torch.testing.assert_close(epoch_targets(a), epoch_targets(b))
    assert not torch.equal(epoch_targets(a), epoch_targets(dataset.loader("train", 8, seed=1)))  # epoch 1 ≠ 0
    for batch in dataset.loader("train", 8):
        validate_batch(batch, dataset.specs, 4, 3, 2, require_target=True)
        assert batch.batch_size[0] == 8  # drop_last for training

    shards = [dataset.loader("train", 5, seed=2, rank=r, world_size=2) for r in range(2)]
    ids = [s._ids() for s in shards]
    assert len(ids[0]) == len(ids[1]) == len(train) // 2
    assert not set(ids[0].tolist()) & set(ids[1].tolist())

    for split in ("val", "test"):
        loader = dataset.loader(split, 4)
        targets = epoch_targets(loader)
        torch.testing.assert_close(targets, dataset.batch(dataset.split_windows[split]).get(TARGET))
        assert len(loader) == -(-len(dataset.split_windows[split]) // 4)


def test_parquet_nulls_read_as_absent_like_nan(synthetic_copy, tmp_path):
    # lerobot's aggregate_datasets (the recorder's multi-worker path) writes NaN as parquet nulls.
    nan_presence = open_quietly(synthetic_config(synthetic_copy, tmp_path / "nan")).presence["force"]
    data_file = next((synthetic_copy / "data").rglob("*.parquet"))
    frames = pd.read_parquet(data_file)
    frames[FORCE_FEATURE] = [
        [None if np.isnan(v) else float(v) for v in row] for row in frames[FORCE_FEATURE]
    ]
    frames.to_parquet(data_file)
    dataset = open_quietly(synthetic_config(synthetic_copy, tmp_path / "null"))
    assert torch.equal(dataset.presence["force"], nan_presence) and not nan_presence.all()
    assert torch.isfinite(all_windows(dataset).get(obs_key("force"))).all()


def test_vector_kind_and_required_vector_modality(synthetic_root, tmp_path):
    modalities = {
        "state": {"feature": STATE_FEATURE, "kind": "vector"},
        "force": {"feature": FORCE_FEATURE, "required": True},
    }
    dataset = open_quietly(synthetic_config(synthetic_root, tmp_path, modalities=modalities))
    batch = all_windows(dataset)
    validate_batch(batch, dataset.specs, 4, 3, 2)
    assert batch.get(obs_key("state")).shape == (len(dataset), 4)
    # A required modality is in every sample: the windows where force is NaN are left out.
    absent = int((~dataset.presence["force"]).sum())
    assert absent > 0 and dataset.report["skipped"]["windows_without_required_modality"] == absent
    in_splits = torch.cat(list(dataset.split_windows.values()))
    assert dataset.presence["force"][in_splits].all() and len(in_splits) == len(dataset) - absent


@pytest.mark.slow
def test_drifting_timestamps_lose_the_camera_with_an_error_unless_synced_by_frame_index(
    drifting_g1_root, g1_root, tmp_path
):
    """A real camera whose rows carry wall-clock stamps: decoding at them loses it on every frame, an
    error naming the sync option; synced by frame index it decodes exactly the original's frames."""

    def g1_config(root, **overrides):
        return DataConfig.from_dict(
            {
                "root": str(root),
                "cache_dir": str(tmp_path),
                "history": 5,
                "horizon": 5,
                "image_size": [16, 16],
                "modalities": {"cam": "observation.images.cam_high", "state": "observation.state"},
                "target": {"feature": "observation.state", "relative": True},
                **overrides,
            }
        )

    with pytest.raises(
        ValueError,
        match=r"modality 'cam' \(observation\.images\.cam_high\) is absent on 100\.0% of the 2316 frames.*"
        r"FrameTimestampError.*mmf-rl inspect.*data\.video_sync=frame_index",
    ):
        WindowDataset(g1_config(drifting_g1_root))
    synced = WindowDataset(g1_config(drifting_g1_root, video_sync="frame_index"))
    assert synced.presence["cam"].all() and not synced.report["undecodable_files"]
    original = WindowDataset(g1_config(g1_root))
    frames = [TensorDict.load_memmap(d.cache_path / "frames") for d in (synced, original)]
    assert torch.equal(*(f.get(obs_key("cam")).as_subclass(torch.Tensor) for f in frames))


def test_partial_windows_keep_a_modality_present_at_some_steps(synthetic_root, tmp_path):
    whole = open_quietly(synthetic_config(synthetic_root, tmp_path))
    partial = open_quietly(synthetic_config(synthetic_root, tmp_path, partial_windows=True))
    assert torch.equal(partial.window_start, whole.window_start)
    batch, before = all_windows(partial), all_windows(whole)
    steps = batch.get(present_steps_key("force"))
    present = batch.get(present_key("force"))
    # Present throughout before -> every step present now; a window with a NaN step is kept.
    assert steps[before.get(present_key("force"))].all()
    assert torch.equal(present, steps.any(1)) and bool((present & ~steps.all(1)).any())
    assert bool((present & ~before.get(present_key("force"))).any())
    force = batch.get(obs_key("force"))
    assert torch.isfinite(force).all() and not force[~steps].any()
    assert torch.equal(
        force[before.get(present_key("force"))],
        before.get(obs_key("force"))[before.get(present_key("force"))],
    )
    assert present_steps_key("force") not in before.keys(True)


def recorded_push_config(root, cache_dir, target: dict) -> DataConfig:
    """The push data config on the tiny recorded push dataset, at 16 px, with this ``target``."""
    return push_data_config(root, cache_dir, image_size=[16, 16], target=target)


def test_target_relative_to_the_gripper_on_recorded_pushes(recorded_push_root, tmp_path):
    """The object's position minus the gripper's (x, y) at the last observed frame, read from the
    recorder's own columns."""
    from mmf_rl.record import OBJECT_POSE_KEY, STATE_KEY

    gripper = {"feature": STATE_KEY, "dims": [0, 1]}
    absolute = open_quietly(
        recorded_push_config(recorded_push_root, tmp_path, {"feature": OBJECT_POSE_KEY, "dims": [0, 1]})
    )
    offset = open_quietly(
        recorded_push_config(
            recorded_push_root, tmp_path, {"feature": OBJECT_POSE_KEY, "dims": [0, 1], "relative_to": gripper}
        )
    )
    frames = raw_frames(recorded_push_root)
    ids = torch.arange(len(offset))
    last = offset.window_start[ids] + 3  # the last observed frame (history 4, stride 1)
    grip = torch.from_numpy(column(frames, STATE_KEY)[:, :2])[last][:, None]
    future_abs = absolute.normalizer.denormalize_target(absolute.batch(ids).get(TARGET))
    batch = offset.batch(ids)
    torch.testing.assert_close(offset.normalizer.denormalize_target(batch.get(TARGET)), future_abs - grip)
    past_abs = absolute.normalizer.denormalize_target(absolute.batch(ids).get(TARGET_PAST))
    torch.testing.assert_close(offset.normalizer.denormalize_target(batch.get(TARGET_PAST)), past_abs - grip)
    train = offset.split_windows["train"]
    torch.testing.assert_close(
        offset.normalizer.stats["target/mean"], (future_abs - grip)[train].reshape(-1, 2).mean(0)
    )
    # The reference is part of the cache's content: its own cache, not the absolute one's.
    assert offset.cache_path != absolute.cache_path


@pytest.mark.parametrize(
    "relative_to, extra, message",
    [
        ({"feature": "observation.gripper"}, {}, "'observation.gripper' is not in the dataset"),
        ({"feature": "observation.state", "dims": [0, 40]}, {}, "dims [0, 40] out of range"),
        ({"feature": "observation.state", "dims": [0, 1, 2]}, {}, "give one reference dim per target dim"),
        ({"feature": "observation.state", "dims": [0, 1]}, {"relative": True}, "keep one"),
    ],
)
def test_target_relative_to_errors_name_the_problem(
    recorded_push_root, tmp_path, relative_to, extra, message
):
    from mmf_rl.record import OBJECT_POSE_KEY

    target = {"feature": OBJECT_POSE_KEY, "dims": [0, 1], "relative_to": relative_to, **extra}
    with pytest.raises(ValueError, match=re.escape(message)):
        open_quietly(recorded_push_config(recorded_push_root, tmp_path, target))
