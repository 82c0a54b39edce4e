"""benchmarks/mult_gap.py, run as a script: a tiny run of its hybrids on the push data recorded by the
fixtures writes the table of every row and the summary line."""

from __future__ import annotations

import json
import re

import pytest

from mmf_rl.models import MODELS
from tests.benchmarks.conftest import study_out
from tests.conftest import run_bench

NUMBER = r"(\d+\.\d{3}|-)"
SUMMARY = re.compile(
    rf"summary: MulT all {NUMBER}; MulT on the paper's tokens {NUMBER} \(fixed-query readout {NUMBER}\); "
    rf"paper {NUMBER}"
)
TINY_ROWS = ["paper", "MulT on the paper's tokens, fixed-query readout", "paper, pair tokens"]


@pytest.fixture
def registered_models():
    """The script registers its hybrids when it runs; other tests see the built-in models only."""
    before = dict(MODELS)
    yield
    MODELS.clear()
    MODELS.update(before)


def test_a_tiny_run_writes_every_row_and_the_summary_line(
    recorded_push_root, push_cache_dir, tmp_path, registered_models
):
    out = study_out(tmp_path, push_cache_dir)
    run = run_bench("mult_gap", "--tiny", "--data", str(recorded_push_root), "--out", str(out), cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    line = run.stdout.strip().splitlines()[-1]
    match = SUMMARY.fullmatch(line)
    assert match, line
    assert match.group(1) == match.group(2) == "-"  # MulT and MulT on the paper's tokens: not tiny rows
    assert match.group(3) != "-" and match.group(4) != "-"
    text = (out / "results.md").read_text()
    assert text.strip().splitlines()[-1] == line
    columns = "all | w/o force | w/o image | w/o proprio | force only | image only | proprio only | mean of 7"
    assert f"| model | seeds | {columns} |" in text
    rows = [row for row in text.splitlines() if row.startswith("| ") and " | 1 | " in row]
    assert [row.split(" | ")[0][2:] for row in rows] == TINY_ROWS
    assert all(len(row.split(" | ")) == 10 and "| -" not in row for row in rows)
    results = json.loads((out / "results.json").read_text())
    assert sorted(results["cells"]) == sorted(TINY_ROWS)
    assert results["summary"]["paper"] == pytest.approx(results["cells"]["paper"]["all"]["mean"])
    # Every row's fit: its all-sensor MSE on training windows beside the test cell's.
    assert sorted(results["fit"]) == sorted(TINY_ROWS)
    for label, fit in results["fit"].items():
        assert fit["test"] == pytest.approx(results["cells"][label]["all"]["mean"]) and fit["train"] > 0
    assert "## Fit: every sensor, training windows against test" in text


def test_unknown_rows_are_refused_before_anything_runs(tmp_path, registered_models):
    run = run_bench("mult_gap", "--entries", "paper", "MulT, fixed query", cwd=tmp_path)
    assert run.returncode == 2 and "--entries: unknown ['MulT, fixed query']" in run.stderr
