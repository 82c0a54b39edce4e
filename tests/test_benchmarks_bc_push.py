"""benchmarks/bc_push.py end to end with tiny budgets, run as a user runs it (``mmf-rl bench bc``, in
this process: a subprocess would add its imports to the test's time): builds the forecaster and
both policies, plays, writes the results and ends with the summary line."""

from __future__ import annotations

import json
import re

import pytest

from mmf_rl.cli import main as cli
from mmf_rl.rl import BCPolicy
from tests.conftest import push_train_overrides


@pytest.mark.parametrize("latched", [None, "precision"])
def test_bc_push_builds_what_it_lacks_and_ends_with_the_summary(
    recorded_push_root, tmp_path, capsys, latched
):
    work = tmp_path / "work"
    tiny_forecaster = push_train_overrides(
        recorded_push_root, tmp_path / "cache", work / "forecaster", steps=3
    )
    argv = [
        *("--quick", "--work", str(work), "--data", str(recorded_push_root)),
        *("--forecaster-override", *tiny_forecaster),
        *("--bc-steps", "3", "--bc-batch-size", "16", "--bc-seeds", "0"),
        *("--bc-d-model", "8", "--bc-hidden", "16", "--bc-image-channels", "8", "16"),
        *("--episodes", "1", "--outage", "episode"),
        *(("--latched-forecast", latched) if latched else ()),
    ]
    assert cli(["bench", "bc", *argv]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    pct = r"\d+%/\d+%"
    assert re.fullmatch(
        rf"summary: BC success all {pct}, no-camera {pct}, no-force {pct} \(without/with forecasts\); "
        r"camera loss without/with forecasts episode -?\d+/-?\d+ pts "
        r"\(target with <= without/2: met for [01] of 1 outage types\)",
        last,
    ), last
    results = json.loads((work / "results.json").read_text())
    conditions = ["all", "no-camera (episode)", "no-force (episode)"]
    expected = {f"BC {v} forecasts | {c}" for v in ("without", "with") for c in conditions} | {
        "scripted | all"
    }
    assert set(results["rows"]) == expected
    assert set(results["validation_errors"]) == {"without", "with"}
    with_run = f"bc_with_latched_{latched}_forecasts_seed0" if latched else "bc_with_forecasts_seed0"
    for run in ("bc_without_forecasts_seed0", with_run):
        assert (work / run / "checkpoints" / "last").is_file()
    assert BCPolicy.from_checkpoint(work / with_run / "checkpoints").config.latched_forecast == latched
