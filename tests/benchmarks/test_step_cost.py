"""benchmarks/step_cost.py, run as a script: every variant trains and gets its ratio to MulT."""

from __future__ import annotations

from tests.conftest import run_bench

VARIANTS = [
    "forecaster (default)",
    "forecaster, raw tokens (the paper)",
    "forecaster, L_mis teacher detached",
    "forecaster, per-frame image tokens",
    "MulT trained for missing sensors (experiment=robust_mult)",
    "MulT",
]


def test_prints_one_ratio_per_model(tmp_path):
    argv = ["--batch-size", "4", "--image-size", "16", "--steps", "1", "--rounds", "2", "--threads", "1"]
    run = run_bench("step_cost", *argv, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == VARIANTS
    assert all(" ms/step, " in line and line.endswith("x MulT") for line in lines)
    assert lines[-1].endswith("1.00x MulT")
