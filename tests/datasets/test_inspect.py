"""`mmf-rl inspect`: the report (features, cameras, NaN spans, outages) and the suggested config."""

import json
import shutil
import warnings

import numpy as np
import pytest
import yaml

from benchmarks.synthetic.dataset import (
    FORCE_FEATURE,
    IMAGE_FEATURE,
    IMAGE_VALID_FEATURE,
    POSE_FEATURE,
    STATE_FEATURE,
)
from mmf_rl.cli import main as cli
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.inspect import (
    _motion_ratio,
    choose_target,
    config_comments,
    config_text,
    inspect_dataset,
    ranked_targets,
    suggested_data_config,
)
from mmf_rl.datasets.provenance import PROVENANCE_FILE
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import (
    CLOCK_OFFSET_S,
    CLOCK_RATE,
    EPISODE_LENGTHS,
    INVALID_IMAGE_EPISODE,
    NAN_FORCE_EPISODE,
    SO101_ROOT,
    UNCONVENTIONAL_ACTIONS,
    UNCONVENTIONAL_CAMERA,
    UNCONVENTIONAL_EPISODES,
    UNCONVENTIONAL_STATE,
    needs_so101,
)
from tests.datasets.test_provenance import SCRIPTED
from tests.test_configuration import readme_commands

FRAMES = sum(EPISODE_LENGTHS)
SPAN = 5  # the fixture's NaN force and invalid camera spans: frames 5..9 of one episode


def test_report_names_features_spans_cameras_and_outages(synthetic_root):
    report = inspect_dataset(synthetic_root)
    assert (report["episodes"], report["frames"], report["fps"]) == (len(EPISODE_LENGTHS), FRAMES, 25)
    assert report["episode_frames"] == EPISODE_LENGTHS
    assert (
        report["features"][FORCE_FEATURE]["shape"] == [3]
        and report["features"][IMAGE_FEATURE]["dtype"] == "video"
    )
    assert report["cameras"] == [IMAGE_FEATURE] and IMAGE_VALID_FEATURE not in report["vectors"]
    force = report["sensors"][FORCE_FEATURE]
    assert force["nonfinite_spans"] == [{"episode": NAN_FORCE_EPISODE, "frames": [5, 9]}]
    assert force["outages"] == {
        "fraction": SPAN / FRAMES,
        "outages": 1,
        "mean_burst": SPAN,
        "max_burst": SPAN,
    }
    camera = report["sensors"][IMAGE_FEATURE]
    assert camera["validity_feature"] == IMAGE_VALID_FEATURE and camera["video_files_missing"] == []
    assert camera["outages"] == {
        "fraction": SPAN / FRAMES,
        "outages": 1,
        "mean_burst": SPAN,
        "max_burst": SPAN,
    }
    assert report["sensors"][STATE_FEATURE]["outages"]["fraction"] == 0
    assert INVALID_IMAGE_EPISODE != NAN_FORCE_EPISODE

    config = suggested_data_config(report)
    assert {name: m["feature"] for name, m in config["modalities"].items()} == {
        "front": IMAGE_FEATURE,
        "state": STATE_FEATURE,
        "force": FORCE_FEATURE,
        "object_pose": POSE_FEATURE,
    }
    assert set(config) == set(
        DataConfig.from_dict(config).to_dict()
    )  # every key: `data.KEY=...` overrides any
    assert config["target"]["feature"] == STATE_FEATURE and config["image_size"] == [32, 32]
    replayed = {"fraction": round(SPAN / FRAMES, 4), "mean_burst": float(SPAN)}
    assert config["missing"] == {"front": replayed, "force": replayed}
    DataConfig.from_dict(config)


def test_camera_declared_but_missing_on_disk(synthetic_copy):
    shutil.rmtree(synthetic_copy / "videos" / IMAGE_FEATURE)
    report = inspect_dataset(synthetic_copy)
    camera = report["sensors"][IMAGE_FEATURE]
    assert camera["video_files_missing"] and all(IMAGE_FEATURE in p for p in camera["video_files_missing"])
    assert camera["episodes_without_video"] == len(EPISODE_LENGTHS) and camera["outages"]["fraction"] == 1.0
    assert "front" not in suggested_data_config(report)["missing"]  # absent throughout: nothing to replay


def test_cli_writes_a_config_that_trains(synthetic_root, tmp_path, capsys):
    path = tmp_path / "configs" / "mine.yaml"
    assert cli(["inspect", str(synthetic_root), "--write-config", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"NaN/Inf: {SPAN} frames in 1 spans" in out and f"episode {NAN_FORCE_EPISODE}, frames 5..9" in out
    assert f"validity flag: {IMAGE_VALID_FEATURE}" in out and f"data config written to {path}" in out
    assert path.read_text().startswith("# Data config suggested by `mmf-rl inspect`")
    assert yaml.safe_load(path.read_text()) == suggested_data_config(inspect_dataset(synthetic_root))
    assert not list(path.parent.glob(".*.tmp"))
    config = DataConfig.from_dict(
        {**yaml.safe_load(path.read_text()), "history": 4, "horizon": 3, "cache_dir": str(tmp_path / "cache")}
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dataset = WindowDataset(config)
    assert {s.name for s in dataset.specs} == set(config.modalities)

    assert cli(["inspect", str(tmp_path / "nowhere")]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_report_says_how_mmf_rl_record_made_the_dataset_when_it_did(synthetic_root, synthetic_copy, capsys):
    assert inspect_dataset(synthetic_root)["provenance"] is None
    assert cli(["inspect", str(synthetic_root)]) == 0
    assert "mmf-rl record" not in capsys.readouterr().out.split("suggested data config")[0]

    (synthetic_copy / PROVENANCE_FILE).write_text(json.dumps(SCRIPTED))
    assert cli(["inspect", str(synthetic_copy)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"dataset {synthetic_copy}"
    assert lines[2].startswith(
        "  recorded by mmf-rl record: 300 episodes of 50 steps, seed 0, steady scripted"
    )
    assert sum("recorded by mmf-rl record" in line for line in lines) == 1

    (synthetic_copy / PROVENANCE_FILE).write_text("{not json")
    assert cli(["inspect", str(synthetic_copy)]) == 1
    assert f"{synthetic_copy / PROVENANCE_FILE}: not valid JSON" in capsys.readouterr().err


@needs_so101
def test_so101_cameras_are_reported_missing():
    report = inspect_dataset(SO101_ROOT)
    for camera in ("observation.images.front", "observation.images.top"):
        assert report["sensors"][camera]["outages"]["fraction"] == 1.0
        assert report["sensors"][camera]["near_misses"] == 0  # no mp4 anywhere under the root
    assert report["sensors"]["observation.state"]["outages"]["fraction"] == 0.0
    config = suggested_data_config(report)
    assert config["target"]["feature"] == "observation.state"
    # No video file: the cameras could never be present, so they are left out, commented out with why.
    assert set(config["modalities"]) == {"action", "state"}
    assert config["image_size"] == [48, 64]  # the left-out cameras' size, for when they are restored
    text = config_text(report, config)
    assert "  # front left out: absent on all 1492 frames (1 video file missing)" in text
    assert "\n  # top: observation.images.top\n" in text


def test_the_readmes_inspect_train_eval_path(synthetic_root, tmp_path, monkeypatch, capsys):
    """The README's own three commands, verbatim (the dataset path put in, a tiny model and run
    appended): inspect writes a config, train takes it as `data=FILE`, eval scores the run."""
    (inspect,) = readme_commands("inspect")
    assert inspect[0] == "/path/to/dataset" and "--write-config" in inspect
    config = inspect[inspect.index("--write-config") + 1]
    (train,) = [argv for argv in readme_commands("train") if f"data={config}" in argv]
    run_dir = next(a.split("=", 1)[1] for a in train if a.startswith("run_dir="))
    (evaluate,) = [argv for argv in readme_commands("eval") if f"checkpoint={run_dir}" in argv]
    monkeypatch.chdir(tmp_path)
    assert cli(["inspect", str(synthetic_root), *inspect[1:]]) == 0
    tiny = [
        "data.history=4",
        "data.horizon=3",
        f"data.cache_dir={tmp_path / 'cache'}",
        "data.split_seed=1",
        "model.d_model=16",
        "model.d_latent=4",
        "model.num_heads=2",
        "model.mlp_hidden=32",
        "model.head_hidden=32",
        "trainer.total_steps=4",
        "trainer.batch_size=8",
        "trainer.eval_every=2",
        "trainer.checkpoint_every=2",
        "trainer.warmup_steps=1",
        "trainer.progress_bar=false",
        "num_workers=0",
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert cli(["train", *train, *tiny]) == 0
        capsys.readouterr()
        assert cli(["eval", *evaluate, "num_samples=2", "plots=false"]) == 0
    assert "| all |" in capsys.readouterr().out


def test_inspect_measures_timestamp_drift_and_writes_frame_index_sync(drifting_g1_root, g1_root, capsys):
    camera = "observation.images.cam_high"
    report = inspect_dataset(drifting_g1_root)
    sync = report["sensors"][camera]["sync"]
    longest = max(report["episode_frames"])
    assert sync["max_drift_s"] == pytest.approx(
        (longest - 1) / report["fps"] * (CLOCK_RATE - 1) + CLOCK_OFFSET_S, rel=1e-3
    )
    assert sync["timestamp_error"].startswith("FrameTimestampError") and sync["frame_index_error"] is None
    assert sync["sampled_frames"] >= 3
    config = suggested_data_config(report)
    assert config["video_sync"] == "frame_index"
    (line,) = [c for c in config_comments(report, config) if "video_sync" in c]
    assert camera in line and f"{sync['max_drift_s']:.3g} s" in line
    assert cli(["inspect", str(drifting_g1_root)]) == 0
    out = capsys.readouterr().out
    assert "sampled frames at the rows' timestamps (tolerance_s=0.0001): FAIL (FrameTimestampError" in out
    assert "by frame index (video_sync: frame_index): decode" in out

    # The original recording: stamps on the k / fps grid, decoded as lerobot does.
    report = inspect_dataset(g1_root)
    sync = report["sensors"][camera]["sync"]
    assert sync["max_drift_s"] < 1e-5 and sync["timestamp_error"] is None
    assert suggested_data_config(report)["video_sync"] == "timestamp"


def test_target_prefers_state_then_environment_state_then_a_vector_without_outages(synthetic_root):
    report = inspect_dataset(synthetic_root)
    assert report["sensors"][FORCE_FEATURE]["outages"]["fraction"] > 0  # NaN spans
    assert choose_target(report) == STATE_FEATURE
    report["vectors"].remove(STATE_FEATURE)
    # The force sensor comes first but has NaN outages: the complete pose is forecast instead.
    assert report["vectors"].index(FORCE_FEATURE) < report["vectors"].index(POSE_FEATURE)
    assert choose_target(report) == POSE_FEATURE
    report["vectors"].append("observation.environment_state")
    report["sensors"]["observation.environment_state"] = report["sensors"][FORCE_FEATURE]
    assert choose_target(report) == "observation.environment_state"


def test_relative_follows_the_motion_ratio():
    episode = np.zeros(400, dtype=np.int64)
    smooth = np.cumsum(np.random.default_rng(0).normal(size=(400, 2)), 0)  # a position: relative
    noise = np.random.default_rng(1).normal(size=(400, 2))  # noise around a level: absolute
    assert _motion_ratio(smooth, episode) < 0.5 and _motion_ratio(noise, episode) > 1.5
    assert _motion_ratio(np.ones((400, 2)), episode) is None


def test_a_camera_that_decodes_neither_way_is_accepted_absent_with_the_error(synthetic_copy, tmp_path):
    video = next((synthetic_copy / "videos").rglob("*.mp4"))
    video.write_bytes(b"not an mp4 file")
    report = inspect_dataset(synthetic_copy)
    sync = report["sensors"][IMAGE_FEATURE]["sync"]
    assert sync["timestamp_error"].startswith("RuntimeError") and sync["frame_index_error"].startswith(
        "RuntimeError"
    )
    config = suggested_data_config(report)
    assert config["video_sync"] == "timestamp" and config["modalities"]["front"]["allow_absent"]
    assert any("decode neither" in c and "RuntimeError" in c for c in config_comments(report, config))
    # As written, the config trains (the camera absent, with the decoder's warning).
    config = DataConfig.from_dict({**config, "history": 4, "horizon": 3, "cache_dir": str(tmp_path)})
    with pytest.warns(UserWarning, match=rf"{video.name} \(undecodable"):
        assert not WindowDataset(config).presence["front"].any()


# --- a recording not named like LeRobot's own (issue 55): `state`, `actions`, `image` under video/ ---


def test_target_is_the_feature_named_state_not_the_actions_listed_before_it(unconventional_root):
    report = inspect_dataset(unconventional_root)
    assert report["vectors"] == [UNCONVENTIONAL_ACTIONS, UNCONVENTIONAL_STATE]  # both complete
    config = suggested_data_config(report)
    assert config["target"]["feature"] == UNCONVENTIONAL_STATE
    rule, alternatives = config_comments(report, config)[:2]
    assert rule.startswith(
        f'# target {UNCONVENTIONAL_STATE}: picked by the rule "named as a state (state, *.state, '
        'observation.*state*)"'
    )
    assert alternatives.startswith(
        f"# target alternatives, best first: {UNCONVENTIONAL_ACTIONS} [named as an action or command"
    )


def test_targets_rank_by_meaning_then_outages():
    vectors = {  # feature: fraction of frames absent, in the dataset's order
        "action.joint_pos": 0.0,
        "cmd_vel": 0.0,
        "observation.force": 0.0,
        "qpos": 0.0,
        "observation.robot_state": 0.3,
        "robot.state": 0.6,  # absent on most frames: after every other
        "joint_states": 0.0,
        "observation.object_pose": 0.0,
        "temperature": 0.0,
    }
    report = {
        "root": "/data/x",
        "features": {},
        "vectors": list(vectors),
        "sensors": {f: {"outages": {"fraction": a}} for f, a in vectors.items()},
    }
    assert [f for f, _ in ranked_targets(report)] == [
        "joint_states",  # named as a state, complete
        "observation.robot_state",  # named as a state, 30% absent
        "qpos",  # named as a position
        "observation.object_pose",
        "observation.force",  # another observation
        "temperature",  # another vector
        "action.joint_pos",  # commands, whatever else their name says
        "cmd_vel",
        "robot.state",
    ]
    with pytest.raises(ValueError, match=r"/data/x: the dataset has no numeric vector feature"):
        ranked_targets({**report, "vectors": []})


def test_a_camera_absent_on_every_frame_is_left_out_as_a_commented_out_entry(
    unconventional_root, tmp_path, capsys
):
    path = tmp_path / "mine.yaml"
    assert cli(["inspect", str(unconventional_root), "--write-config", str(path)]) == 0
    out = capsys.readouterr().out
    camera = out[out.index(f"  {UNCONVENTIONAL_CAMERA} (camera)") :]
    assert camera.splitlines()[1] == (
        "    left out of the suggested config (a commented-out entry): absent on every frame"
    )
    text = path.read_text()
    entry = (
        f"modalities:\n  # {UNCONVENTIONAL_CAMERA} left out: absent on all "
        f"{sum(UNCONVENTIONAL_EPISODES)} frames ({len(UNCONVENTIONAL_EPISODES)} video files missing; "
    )
    assert entry in text and f"\n  # {UNCONVENTIONAL_CAMERA}: {UNCONVENTIONAL_CAMERA}\n" in text
    written = yaml.safe_load(text)
    assert set(written["modalities"]) == {UNCONVENTIONAL_ACTIONS, UNCONVENTIONAL_STATE}
    assert written["image_size"] == [16, 32]
    # Uncommented, the entry is the camera's modality.
    restored = yaml.safe_load(text.replace(f"  # {UNCONVENTIONAL_CAMERA}: ", f"  {UNCONVENTIONAL_CAMERA}: "))
    assert restored["modalities"][UNCONVENTIONAL_CAMERA] == UNCONVENTIONAL_CAMERA
    # As written, the config builds its windows with no camera to warn about.
    config = DataConfig.from_dict({**written, "history": 3, "horizon": 2, "cache_dir": str(tmp_path / "c")})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert {s.name for s in WindowDataset(config).specs} == set(written["modalities"])


def test_every_sensor_absent_everywhere_is_an_error_naming_the_causes(unconventional_root):
    report = inspect_dataset(unconventional_root)
    for feature in report["vectors"]:
        report["sensors"][feature]["outages"]["fraction"] = 1.0
        report["sensors"][feature]["nonfinite_frames"] = report["frames"]
    with pytest.raises(ValueError, match=r"every sensor is absent on every frame \(image: 8 video files"):
        suggested_data_config(report)


def test_video_files_under_a_near_miss_folder_are_reported_with_the_rename(unconventional_root, capsys):
    report = inspect_dataset(unconventional_root)
    camera = report["sensors"][UNCONVENTIONAL_CAMERA]
    assert camera["episodes_without_video"] == len(UNCONVENTIONAL_EPISODES)
    assert camera["near_misses"] == len(UNCONVENTIONAL_EPISODES) and camera["renames"] == [
        ["video", "videos"]
    ]
    assert camera["sync"] is None  # never read where info.json does not say they are
    assert cli(["inspect", str(unconventional_root)]) == 0
    assert (
        f"    8 of them are under a near-miss path (not read there): in {unconventional_root} rename "
        "video to videos\n"
    ) in capsys.readouterr().out


def _renames_of(root):
    return inspect_dataset(root)["sensors"][UNCONVENTIONAL_CAMERA]["renames"]


def test_near_miss_chunk_and_file_names_are_reported_file_by_file(unconventional_root, tmp_path, capsys):
    root = shutil.copytree(unconventional_root, tmp_path / "copy")
    (root / "videos").mkdir()  # another camera's folder, in place: the camera's own folder is renamed
    assert _renames_of(root) == [["video/image", "videos/image"]]
    (root / "video" / "image").rename(root / "videos" / "image")
    chunk = root / "videos" / "image" / "chunk-000"
    chunk.rename(chunk.with_name("chunk_0"))
    assert _renames_of(root) == [["videos/image/chunk_0", "videos/image/chunk-000"]]
    for video in sorted((root / "videos" / "image" / "chunk_0").iterdir()):
        video.rename(video.with_name(video.name.replace("-", "_")))
    renames = _renames_of(root)
    assert len(renames) == len(UNCONVENTIONAL_EPISODES) and renames[0] == [
        "videos/image/chunk_0/file_000.mp4",
        "videos/image/chunk-000/file-000.mp4",
    ]
    assert cli(["inspect", str(root)]) == 0
    report = capsys.readouterr().out.split("suggested data config")[0]
    (line,) = [line for line in report.splitlines() if "near-miss" in line]
    assert line.endswith("videos/image/chunk-000/file-002.mp4 (and 5 more like them)")


def test_data_files_under_a_near_miss_folder_are_an_error_with_the_rename(
    unconventional_root, tmp_path, capsys
):
    root = shutil.copytree(unconventional_root, tmp_path / "copy")
    (root / "data" / "chunk-000").rename(root / "data" / "chunk_000")
    assert cli(["inspect", str(root)]) == 1
    err = capsys.readouterr().err
    assert f"{root / 'meta' / 'info.json'}: `data_path` 'data/chunk-{{chunk_index:03d}}" in err
    assert f"data file(s) that are missing, e.g. {root}/data/chunk-000/file-000.parquet" in err
    assert f"not read there: in {root} rename data/chunk_000 to data/chunk-000, then run" in err
