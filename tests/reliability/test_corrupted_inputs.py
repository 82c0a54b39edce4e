"""Damaged dataset files: a truncated video, statistics that are NaN or zero."""

import json
import warnings

import numpy as np
import pytest
import torch

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import WindowDataset
from tests.conftest import push_train_overrides
from tests.reliability.conftest import edit_frames, push_data_config

FORCE_DIMS, PROPRIO_DIMS = 6, 17


def test_truncated_mp4_makes_the_camera_absent_with_a_warning_naming_the_file(push_copy, tmp_path):
    [video] = (push_copy / "videos").rglob("*.mp4")
    video.write_bytes(video.read_bytes()[: video.stat().st_size * 2 // 5])
    # More than half of the frames lose their camera: an error naming the file, unless accepted.
    with pytest.raises(ValueError, match=rf"'image'.*absent on [\d.]+% .*{video.name}.*allow_absent=true"):
        WindowDataset(push_data_config(push_copy, tmp_path / "cache"))
    accepted = {
        "image": {"feature": "observation.images.front", "allow_absent": True},
        "force": "observation.force",
        "proprio": "observation.state",
    }
    with pytest.warns(UserWarning, match=rf"{video.name} \(undecodable"):
        dataset = WindowDataset(push_data_config(push_copy, tmp_path / "cache", modalities=accepted))
    image = dataset.presence["image"]
    assert not image.all(), "the episodes past the truncation have no camera"
    assert dataset.presence["force"].all() and dataset.presence["proprio"].all()
    batch = dataset.batch(torch.arange(len(dataset)))
    assert not batch.get(("obs", "image"))[~image].any(), "an undecoded camera window holds no stale pixels"


def constant_first_proprio(frames) -> None:
    for state in frames["observation.state"]:
        state[0] = 0.25


def test_stats_json_with_nan_and_zero_std_still_trains_with_finite_normalisation(push_copy, tmp_path):
    # lerobot's own statistics are wrong: NaN force, zero std everywhere ...
    stats_path = push_copy / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text())
    for feature in stats.values():
        if "std" in feature:
            feature["std"] = np.zeros_like(np.asarray(feature["std"], dtype=float)).tolist()
    stats["observation.force"]["mean"] = [float("nan")] * FORCE_DIMS
    stats["observation.force"]["std"] = [float("nan")] * FORCE_DIMS
    stats_path.write_text(json.dumps(stats))
    # ... and proprio[0] is constant: its std over the training split is 0.
    edit_frames(push_copy, constant_first_proprio)

    run = tmp_path / "run"
    assert (
        cli(
            [
                "train",
                *push_train_overrides(push_copy, tmp_path / "cache", run, steps=3),
                "data.std_floor=0.01",
            ]
        )
        == 0
    )
    checkpoint = load_checkpoint(run / "checkpoints")
    assert all(torch.isfinite(v).all() for v in checkpoint.tensors.values()), checkpoint.tensors
    assert checkpoint.tensors["proprio/std"][0] == pytest.approx(0.01), (
        "a constant feature gets the std floor"
    )
    assert (checkpoint.tensors["proprio/std"][1:] > 0.01).any() and (
        checkpoint.tensors["force/std"] > 0
    ).all()
    assert checkpoint.trainer_state["nonfinite_total"] == 0

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        dataset = WindowDataset(push_data_config(push_copy, tmp_path / "cache"))
    batch = dataset.batch(dataset.split_windows["train"])
    assert all(
        torch.isfinite(batch.get(key)).all()
        for key in batch.keys(True, True)
        if batch.get(key).is_floating_point()
    )
