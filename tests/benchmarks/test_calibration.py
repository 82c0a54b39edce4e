"""benchmarks/calibration.py, run as a script: re-evaluating trained runs under each eval latent, on
recorded push data."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import run_bench

SUMMARY = re.compile(
    r"summary: (\S+) (\S+): MSE all (\S+); coverage 50% (\S+)-(\S+), 90% (\S+)-(\S+) over (\d+) subsets; "
    r"width 90% (\S+)-(\S+), CRPS (\S+)-(\S+)$"
)


def calibration(argv: list[str]) -> int:
    """Run the script on ``argv``; its stdout is printed here, so ``capsys`` sees it."""
    run = run_bench("calibration", *argv, cwd=Path.cwd())
    print(run.stdout, end="")
    print(run.stderr, end="", file=sys.stderr)
    return run.returncode


@pytest.fixture(scope="module")
def learned_runs(recorded_push_root, push_cache_dir, tmp_path_factory):
    """Two seeds of a tiny learned-prior forecaster, as a benchmark entry's ``<entry>/seed<k>``."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.trainers.training import train
    from tests.conftest import push_train_overrides

    base = tmp_path_factory.mktemp("calibration")
    runs = []
    for seed in (0, 1):
        run = base / "learned" / f"seed{seed}"
        overrides = push_train_overrides(recorded_push_root, push_cache_dir, run)
        train(compose_config("train", [*overrides, "model.prior=learned", f"trainer.seed={seed}"]))
        runs.append(run)
    return runs


def test_each_latent_is_scored_on_the_same_windows_and_summarised(learned_runs, tmp_path, capsys):
    out = tmp_path / "out"
    argv = [*map(str, learned_runs), "--out", str(out), "--num-samples", "3", "--predictive-samples", "4"]
    assert calibration(argv) == 0
    lines = [m.groups() for m in map(SUMMARY.match, capsys.readouterr().out.splitlines()) if m]
    assert [(group, latent) for group, latent, *_ in lines] == [
        ("learned", "mean"),
        ("learned", "predictive"),
    ]
    for _, _, mse, low50, high50, low90, high90, _, *sharpness in lines:
        assert float(mse) > 0 and 0 <= float(low50) <= float(high50) <= 1 and float(low90) <= float(high90)
        low_width, high_width, low_crps, high_crps = map(float, sharpness)
        assert 0 < low_width <= high_width and 0 < low_crps <= high_crps
    result = json.loads((out / "results.json").read_text())
    table = result["tables"]["learned"]
    assert table["mean"].keys() == table["predictive"].keys()
    # Each cell is the mean over the two seeds' own evaluations, written where the docstring says.
    for latent in ("mean", "predictive"):
        per_run = [
            json.loads((out / "learned" / run.name / latent / "results.json").read_text())
            for run in learned_runs
        ]
        assert per_run[0]["eval_latent"] == latent
        expected = sum(s["subsets"]["all"]["coverage_90"] for s in per_run) / 2
        assert table[latent]["all"]["coverage_90"] == pytest.approx(expected)


def test_finished_evaluations_are_reused(learned_runs, tmp_path):
    out = tmp_path / "out"
    argv = [str(learned_runs[0]), "--out", str(out), "--num-samples", "0", "--latents", "mean"]
    assert calibration(argv) == 0
    written = out / "learned" / learned_runs[0].name / "mean" / "results.json"
    before = (written.stat().st_mtime_ns, written.read_bytes())
    assert calibration(argv) == 0
    assert (written.stat().st_mtime_ns, written.read_bytes()) == before  # read back, not evaluated again


def test_a_directory_that_is_not_a_run_is_refused(tmp_path, capsys):
    assert calibration([str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "not `mmf-rl train` run directories (no checkpoints/ inside)" in capsys.readouterr().err


def test_a_latent_a_run_s_model_lacks_is_refused_before_any_scoring(learned_runs, tmp_path, capsys):
    """A MulT run has no eval latent: the default --latents are refused for it up front, naming it."""
    mult = tmp_path / "mult" / "seed0"
    (mult / "checkpoints").mkdir(parents=True)
    (mult / "config.yaml").write_text("model:\n  name: mult\n")
    out = tmp_path / "out"
    assert calibration([str(learned_runs[0]), str(mult), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"--latents mean predictive: these runs' models have no eval latent: ['{mult}']" in err
    assert "--latents as-trained" in err and not out.exists()  # nothing scored


def test_recalibrate_scores_raw_and_a_val_recalibrated_copy_per_method_and_leaves_the_run_alone(
    learned_runs, tmp_path, capsys
):
    from safetensors.torch import load_file

    run = learned_runs[0]
    stored = sorted(p for p in run.rglob("*") if p.is_file() and "eval" not in p.parts)
    before = {p: p.read_bytes() for p in stored}
    out = tmp_path / "out"
    argv = [str(run), "--out", str(out), "--num-samples", "0", "--latents", "mean"]
    methods = ["--methods", "coverage", "temperature"]
    assert calibration([*argv, "--recalibrate", "--min-windows", "4", *methods]) == 0
    lines = [m.groups() for m in map(SUMMARY.match, capsys.readouterr().out.splitlines()) if m]
    assert [(group, latent) for group, latent, *_ in lines] == [
        ("learned", "mean:raw"),
        ("learned", "mean:coverage"),
        ("learned", "mean:temperature"),
    ]
    assert {p: p.read_bytes() for p in stored} == before and sorted(
        p for p in run.rglob("*") if p.is_file() and "eval" not in p.parts
    ) == stored
    copies = out / "learned" / run.name / "mean"
    factors = {
        v: load_file(copies / v / "model.safetensors")["scale_calibration.factors"]
        for v in ("raw", "coverage", "temperature")
    }
    assert torch.equal(factors["raw"], torch.ones_like(factors["raw"]))  # the run's own fit reset
    assert not torch.equal(factors["coverage"], factors["raw"])
    assert not torch.equal(factors["coverage"], factors["temperature"])
    for method in ("coverage", "temperature"):
        recalibrated = json.loads((copies / method / "eval" / "results.json").read_text())
        assert recalibrated["scale_calibration"]["split"] == "val" and recalibrated["split"] == "test"
        assert recalibrated["scale_calibration"]["method"] == method
        assert recalibrated["scale_calibration"]["factors"] == factors[method].tolist()
    table = json.loads((out / "results.json").read_text())["tables"]["learned"]
    # The same test windows and point forecasts; only the scale (so the coverage and width) changes.
    for subset, row in table["mean:raw"].items():
        assert table["mean:coverage"][subset]["mse"] == pytest.approx(row["mse"])
    assert any(
        table["mean:coverage"][s]["coverage_90"] != row["coverage_90"] for s, row in table["mean:raw"].items()
    )
    assert any(
        table["mean:coverage"][s]["width_90"] != row["width_90"] for s, row in table["mean:raw"].items()
    )
