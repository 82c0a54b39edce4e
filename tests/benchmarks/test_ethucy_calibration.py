"""The ETH/UCY calibration benchmark's arithmetic (benchmarks/ethucy_calibration.py): the factor each
scene needs, the table and the summary line. Its runs are the ETH/UCY benchmark's (tested there)."""

import pytest
import torch

from benchmarks import ethucy_calibration as bench
from mmf_rl.eval.scale_fit import StandardisedErrors
from mmf_rl.models.scale_calibration import pattern_name

NAMES = ["trajectory", "neighbours", "scene"]


def errors(scale: float, seed: int) -> StandardisedErrors:
    """Standard-normal errors ``scale`` times wider with every modality present, and unit ones with the
    trajectory alone."""
    g = torch.Generator().manual_seed(seed)
    values = {7: scale * torch.randn(400, 12, 2, generator=g), 1: torch.randn(400, 12, 2, generator=g)}
    return StandardisedErrors(NAMES, {i: 400 for i in values}, {i: v.abs() for i, v in values.items()})


def test_each_scene_needs_the_factor_of_its_errors_with_every_modality_present():
    assert pattern_name(7, NAMES) == "trajectory+neighbours+scene"
    found = {("a+b", "a"): errors(4.0, 0), ("a+c", "a"): errors(4.4, 1), ("a+b", "b"): errors(2.0, 2)}
    factors = bench.scene_factors(found)
    assert sorted(factors) == ["a", "b"] and len(factors["a"]) == 2
    # Gaussian errors s times the scale: the 90% factor is s (the trajectory-alone pattern is not read).
    assert factors["a"] == pytest.approx([4.0, 4.4], rel=0.05)
    assert factors["b"] == pytest.approx([2.0], rel=0.05)


def row(coverage_90: float) -> dict:
    return {"coverage_50": 0.5, "coverage_90": coverage_90, "width_90": 1.0, "crps": 0.3}


def test_a_fold_is_within_the_band_only_when_every_mode_is():
    folds = {
        "eth": {
            "val": {"all": row(0.72), "trajectory_only": row(0.74)},
            "held-out scenes": {"all": row(0.86)},
        },
        "hotel": {
            "val": {"all": row(0.93)},
            "held-out scenes": {"all": row(0.96), "without_scene": row(0.9)},
        },
    }
    factors = {"eth": [7.2, 7.9], "hotel": [2.3, 2.5]}
    line = bench.summary(factors, folds)
    assert line.startswith("summary: test 90% coverage (val | held-out scenes fit) eth 0.72-0.74 | 0.86-0.86")
    assert "within 0.85-0.95: 1 | 1 of 2 folds" in line  # hotel's val fit; eth's held-out-scene fit
    assert line.endswith("90% factor each scene needs: eth 7.20-7.90 hotel 2.30-2.50")
    page = bench.markdown(factors, folds)
    assert "| eth | 7.20-7.90 |" in page and "| hotel | held-out scenes | 0.50-0.50 | 0.90-0.96 |" in page


def test_a_fold_run_is_trained_and_scored_as_bench_ethucy_does_so_that_it_can_reuse_it(tmp_path, monkeypatch):
    # bench ethucy reuses a completed fold row by its scores.json, scores and all: this benchmark's fold
    # runs are made by the same function; the pair models are the selection's inner runs.
    args = bench.parse_args(["--out", str(tmp_path / "out"), "--data", str(tmp_path / "data")])
    made = []
    monkeypatch.setattr(bench.bench, "ensure_data", lambda *a: 0.0)
    monkeypatch.setattr(bench, "write_held_out_configs", lambda *a: None)
    monkeypatch.setattr(bench, "fold_data", lambda args, fold: (f"data of {fold}", {}))
    monkeypatch.setattr(bench, "inner_run", lambda args, budget, pair, *rest: made.append(("inner", pair)))
    monkeypatch.setattr(
        bench.bench, "run_trained", lambda args, budget, fold, label, data: made.append((label, data))
    )
    bench.train_all(args)
    folds = [m for m in made if m[0] != "inner"]
    assert folds == [(bench.PAPER, f"data of {fold}") for fold in ("eth", "hotel", "univ", "zara1", "zara2")]
    assert len(made) - len(folds) == 10
