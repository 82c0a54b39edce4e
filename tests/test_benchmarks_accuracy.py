"""benchmarks/accuracy.py, run as a script: its protocol is mmf_rl.compare's (tests/compare); what is
its own (the entries, budgets, the report's header and projections, the summary line) is checked on a
tiny run of the push data recorded by the fixtures."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from tests.conftest import run_bench

SUMMARY = re.compile(
    r"summary: paper model best or tied in (\S+)/(\d+) subsets \(zero-fill baselines\), (\S+)/3 paper "
    r"subsets vs retrained; fusion spread (\S+); mean degradation paper (-?\d+)%, best baseline (\S+)"
)


def accuracy(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_bench("accuracy", *args, cwd=cwd)


def test_a_tiny_run_writes_the_report_and_the_summary_line(recorded_push_root, tmp_path):
    out = tmp_path / "out"
    budget = ["--tiny", "--entries", "paper", "LF-LSTM", "--seeds", "0", "--steps", "2"]
    run = accuracy(*budget, "--data", str(recorded_push_root), "--out", str(out), cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    line = run.stdout.strip().splitlines()[-1]
    match = SUMMARY.fullmatch(line)
    assert match, line
    assert (
        match.group(2) == "7" and match.group(3) == "-" and match.group(4) == "-"
    )  # no retrained, no fusion
    text = (out / "results.md").read_text()
    assert text.startswith("# Missing-modality benchmark (tiny mode)\n\nPush dataset ")
    assert text.strip().splitlines()[-1] == line
    results = json.loads((out / "results.json").read_text())
    assert results["budget"] == {
        "image_size": 32,
        "batch_size": 8,
        "steps": 2,
        "seeds": [0],
        "entries": ["paper", "LF-LSTM"],
        "episodes": 16,
        "retrained_subsets": "paper",
    }
    assert results["subsets"][:3] == ["all", "without_proprio", "without_force"]
    assert results["kinds"] == {"paper": "paper", "LF-LSTM": "zero-fill"}


def test_unknown_entries_are_refused_before_anything_runs(tmp_path):
    run = accuracy("--entries", "paper", "LF-LSMT", "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert run.returncode == 2 and "--entries: unknown ['LF-LSMT']" in run.stderr
    assert not (tmp_path / "out").exists()


def test_runs_of_another_budget_are_refused_before_anything_runs(tmp_path):
    out = tmp_path / "out"
    stale = out / "paper" / "seed0" / "eval" / "window_errors.json"
    stale.parent.mkdir(parents=True)
    stale.write_text(json.dumps({"steps": 3, "batch_size": 8}))
    argv = ["--tiny", "--entries", "paper", "--seeds", "0", "--steps", "2"]
    run = accuracy(*argv, "--data", str(tmp_path / "push"), "--out", str(out), cwd=tmp_path)
    assert run.returncode == 1 and "holds runs of another budget than 2 steps of batch 8" in run.stderr
    assert not (tmp_path / "push").exists()  # refused before recording
