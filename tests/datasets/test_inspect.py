"""`mmf-rl inspect`: the report (features, cameras, NaN spans, outages) and the suggested config."""

import json
import shutil
import warnings

import numpy as np
import pytest
import yaml

from mmf_rl.cli import main as cli
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.inspect import (
    _motion_ratio,
    choose_target,
    config_comments,
    inspect_dataset,
    suggested_data_config,
)
from mmf_rl.datasets.provenance import PROVENANCE_FILE
from mmf_rl.datasets.synthetic import (
    FORCE_FEATURE,
    IMAGE_FEATURE,
    IMAGE_VALID_FEATURE,
    POSE_FEATURE,
    STATE_FEATURE,
)
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import (
    CLOCK_OFFSET_S,
    CLOCK_RATE,
    EPISODE_LENGTHS,
    INVALID_IMAGE_EPISODE,
    NAN_FORCE_EPISODE,
    SO101_ROOT,
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
    assert report["sensors"]["observation.state"]["outages"]["fraction"] == 0.0
    config = suggested_data_config(report)
    assert config["target"]["feature"] == "observation.state"
    # No video file: the cameras are accepted absent, with a comment saying so.
    assert config["modalities"]["front"]["allow_absent"] and config["modalities"]["top"]["allow_absent"]
    assert not config["modalities"]["state"]["allow_absent"]
    assert any(
        "front: allow_absent" in c and "video files are missing" in c for c in config_comments(report, config)
    )


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
