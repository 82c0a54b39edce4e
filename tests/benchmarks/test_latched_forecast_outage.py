"""benchmarks/latched_forecast_outage.py as a user runs it (``mmf-rl bench latch``), on a tiny
forecaster trained on the recorded push data: every rule scored through a camera outage on the
held-out episodes, ending with the summary line. The forecaster of the data config's target is the
session's (`push_forecaster_run`, which the benchmark only reads); the one relative to the gripper is
trained here."""

from __future__ import annotations

import re

import pytest

from mmf_rl.cli import main as cli
from mmf_rl.rl.latched_forecast import RULES
from tests.conftest import push_train_overrides, run_bench

TARGETS = {
    "relative": None,  # the data config's: the session's forecaster
    "relative to the gripper": [
        "data.target.relative=false",
        "data.target.relative_to={feature: observation.state, dims: [0, 1]}",
    ],
}


@pytest.mark.parametrize("target", list(TARGETS))
def test_latch_benchmark_scores_every_rule_and_ends_with_the_summary(
    recorded_push_root, push_cache_dir, tmp_path, request, target
):
    if TARGETS[target] is None:
        run = request.getfixturevalue("push_forecaster_run")
    else:
        run = tmp_path / "run"
        overrides = push_train_overrides(recorded_push_root, push_cache_dir, run, steps=3)
        assert cli(["train", *overrides, *TARGETS[target]]) == 0
    result = run_bench("latch", "--checkpoint", str(run), "--die-at", "8", "20", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    rows = {line.split(":")[0].strip() for line in lines[1:-1]}
    assert rows == {"camera on", *RULES, "fresh, per-step presence"}
    assert all(re.search(r"ade \d+\.\d+, fde \d+\.\d+, nll -?\d+\.\d+", line) for line in lines[1:-1])
    assert re.fullmatch(r"summary: camera outage ADE best '[a-z ,-]+' \(\d+\.\d{4}\)", lines[-1]), lines[-1]
