"""Inf in the data: absent like NaN, never a value that reaches the model or the statistics.

The trainer's own numerical guards are tested in tests/trainers/test_trainer.py (NaN batch
skipped and counted, repeated NaN stops naming the batch, exploding loss names the last good
checkpoint).
"""

import warnings

import numpy as np
import torch

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import WindowDataset
from tests.conftest import push_train_overrides
from tests.reliability.conftest import edit_frames, push_data_config

EPISODE, INF_FORCE_FRAMES, INF_TARGET_FRAME = 0, range(10, 13), 20


def inject_inf(frames) -> None:
    rows = np.flatnonzero(frames["episode_index"].to_numpy() == EPISODE)
    for row in rows[list(INF_FORCE_FRAMES)]:
        frames.at[row, "observation.force"][:] = np.inf
    frames.at[rows[INF_TARGET_FRAME], "observation.object_pose"][0] = -np.inf


def test_inf_in_force_and_target_reads_as_absent_and_trains_finite(push_copy, tmp_path):
    edit_frames(push_copy, inject_inf)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        # Without target_past: only the forecast frames and the relative target's origin (the
        # last observed frame) need a finite target.
        dataset = WindowDataset(push_data_config(push_copy, tmp_path / "cache", include_target_past=False))
    ids = torch.arange(len(dataset))
    starts = dataset.window_start - dataset.window_start[dataset.window_episode == EPISODE].min()
    in_episode = dataset.window_episode == EPISODE
    history, horizon = 4, 3
    # A force window overlapping the Inf frames is absent; one that does not is present.
    overlaps = in_episode & (starts <= INF_FORCE_FRAMES[-1]) & (starts + history > INF_FORCE_FRAMES[0])
    assert overlaps.any() and not dataset.presence["force"][overlaps].any()
    assert dataset.presence["force"][~overlaps].all()
    last_observed = starts + history - 1
    reads_inf_target = (last_observed <= INF_TARGET_FRAME) & (last_observed + horizon >= INF_TARGET_FRAME)
    assert not (in_episode & reads_inf_target).any()
    assert (in_episode & (last_observed == INF_TARGET_FRAME + 1)).any(), "windows right after it are kept"
    batch = dataset.batch(ids)
    for key in ("target", ("obs", "force"), ("obs", "proprio")):
        assert torch.isfinite(batch.get(key)).all() and batch.get(key).abs().max() < 1e3, key

    run = tmp_path / "run"
    assert cli(["train", *push_train_overrides(push_copy, tmp_path / "cache", run, steps=3)]) == 0
    checkpoint = load_checkpoint(run / "checkpoints")
    assert all(torch.isfinite(v).all() for v in checkpoint.tensors.values())
    assert checkpoint.tensors["target/std"].max() < 1, "the target statistics saw no Inf"
    assert checkpoint.trainer_state["nonfinite_total"] == 0
