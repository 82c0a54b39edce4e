"""What the push experiment scripts share: budgets filled into their arguments, merged overrides, the
forecaster calibrated before it forecasts."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import torch

from benchmarks.push.experiment import (
    add_common_arguments,
    calibrated_forecaster,
    merged_overrides,
    resolve_budget,
    train_or_resume,
)
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.models.loading import load_trained_model
from mmf_rl.rl import Demonstrations, ForecastTable, drop_sets
from tests.conftest import push_train_overrides
from tests.rl.conftest import BC_DROPPABLE as DROPPABLE

BUDGETS = {"quick": {"episodes": 20, "outage": ["episode"]}, "full": {"episodes": 50, "outage": ["dies"]}}


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_common_arguments(parser, "mpc")
    return resolve_budget(parser.parse_args(argv), BUDGETS, "mpc")


def test_the_budget_fills_what_is_not_given_and_names_the_work_directory():
    quick = parse("--quick", "--episodes", "3")
    assert (quick.episodes, quick.outage) == (3, ["episode"])
    assert quick.work == quick.out == Path("runs/bench_mpc_quick")
    full = parse("--out", "elsewhere")
    assert (full.episodes, full.outage, full.work, full.out) == (
        50,
        ["dies"],
        Path("runs/bench_mpc_full"),
        Path("elsewhere"),
    )


def test_extra_overrides_replace_the_same_keys():
    base = ["run_dir=a", "trainer.seed=0", "trainer.total_steps=100"]
    assert merged_overrides(base, ["trainer.total_steps=3", "model.d_model=8"]) == [
        "run_dir=a",
        "trainer.seed=0",
        "trainer.total_steps=3",
        "model.d_model=8",
    ]


@pytest.fixture(scope="module")
def uncalibrated_run(recorded_push_root, tmp_path_factory):
    """A tiny forecaster trained without the end-of-run calibration (``calibrate=false``)."""
    from mmf_rl.cli import main as cli

    base = tmp_path_factory.mktemp("uncalibrated")
    overrides = push_train_overrides(recorded_push_root, base / "cache", base / "run", steps=4)
    assert cli(["train", *overrides, "calibrate=false"]) == 0
    return base / "run"


def test_the_forecaster_is_calibrated_once_and_its_forecasts_differ_only_in_scale(
    uncalibrated_run, monkeypatch
):
    checkpoints = uncalibrated_run / "checkpoints"
    assert load_trained_model(checkpoints)[0].scale_calibration.is_identity()
    (model, stats, data_config), fit = calibrated_forecaster(checkpoints)
    assert fit is not None and fit["split"] == "val" and fit["min_windows"] == 32
    factors = model.scale_calibration.factors
    assert fit["factors"] == factors.tolist() and not model.scale_calibration.is_identity()
    assert any(p["fitted"] for p in fit["patterns"])

    # The fit is written with the model: a second call finds it and does not fit again.
    def refit(cfg):
        raise AssertionError("refitted")

    monkeypatch.setattr("mmf_rl.eval.calibration.calibrate", refit)
    assert calibrated_forecaster(checkpoints)[1] == fit
    (plain, _, _), none = calibrated_forecaster(checkpoints, calibrate=False)
    assert none is None and plain.scale_calibration.is_identity()

    # The forecasts of the demonstrations: same means; scales times the factor of the pattern left.
    demonstrations = Demonstrations(WindowDataset(DataConfig.from_dict(data_config)))
    calibrated = ForecastTable.compute(demonstrations, model, stats, DROPPABLE)
    as_trained = ForecastTable.compute(demonstrations, plain, stats, DROPPABLE)
    frames = demonstrations.split_frames["train"]
    torch.testing.assert_close(calibrated.loc[frames], as_trained.loc[frames])
    names = [s.name for s in model.config.modalities]
    for i, dropped in enumerate(drop_sets(DROPPABLE)):
        present = demonstrations.presence(frames)
        kept = torch.stack([present[m] & (m not in dropped) for m in names], 1)
        factor = factors[model.scale_calibration.pattern_index(kept)]
        ratio = calibrated.scale[frames, i] / as_trained.scale[frames, i]
        torch.testing.assert_close(ratio, factor.view(-1, 1, 1).expand_as(ratio))


def test_an_ended_training_is_used_as_it_is_unless_its_config_changed(
    uncalibrated_run, recorded_push_root, monkeypatch
):
    def train(cfg):
        raise AssertionError("trained again")

    monkeypatch.setattr("benchmarks.push.experiment.train", train)
    overrides = [
        *push_train_overrides(
            recorded_push_root, uncalibrated_run.parent / "cache", uncalibrated_run, steps=4
        ),
        "calibrate=false",
    ]
    assert train_or_resume(overrides) == uncalibrated_run.resolve() / "checkpoints"
    with pytest.raises(CheckpointError, match="model.d_model"):
        train_or_resume([*overrides, "model.d_model=8"])
