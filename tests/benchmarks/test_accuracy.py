"""benchmarks/accuracy.py, run as a script: its protocol is mmf_rl.compare's (tests/compare); what is
its own (the entries, budgets, the report's header and projections, the summary line) is checked on a
tiny run of the push data recorded by the fixtures."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import pytest

from benchmarks import accuracy as bench
from mmf_rl.compare import entries as catalogue
from mmf_rl.configuration import compose_config, to_container
from tests.benchmarks.conftest import study_out
from tests.conftest import run_bench

SUMMARY = re.compile(
    r"summary: paper model best or tied in (\S+)/(\d+) subsets \(zero-fill baselines\), (\S+)/3 paper "
    r"subsets vs retrained; fusion spread (\S+); mean degradation paper (-?\d+)%, best baseline (\S+)"
)


def accuracy(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_bench("accuracy", *args, cwd=cwd)


def test_a_tiny_run_writes_the_report_and_the_summary_line(recorded_push_root, push_cache_dir, tmp_path):
    out = study_out(tmp_path, push_cache_dir)
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
    assert results["fit"]["LF-LSTM"]["test"] == pytest.approx(results["cells"]["LF-LSTM"]["all"]["mean"])
    assert "| LF-LSTM | " in text.split("## Fit: every sensor, training windows against test")[1]


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
    assert run.returncode == 1 and "would not train (2 steps of batch 8" in run.stderr
    assert "paper/seed0: 3 steps of batch 8" in run.stderr
    assert not (tmp_path / "push").exists()  # refused before recording


def test_every_mode_names_entries_that_exist_and_the_standard_mode_has_what_its_summary_needs():
    labels = [e.label for e in bench.ENTRIES]
    assert len(set(labels)) == len(labels)
    for name, mode in bench.MODES.items():
        assert mode.entries is None or set(mode.entries) <= set(labels), name
    needed = [catalogue.PAPER, *catalogue.ZERO_FILL, *catalogue.RETRAINED, *catalogue.FUSION_ABLATIONS]
    assert {e.label for e in needed} <= set(bench.STANDARD.entries)
    assert bench.FULL.entries is None  # the full mode keeps the searches the defaults came from


def test_no_entry_trains_the_same_config_as_another():
    """An override that restates a default (``model.decoder_input=mixed`` once it became the default)
    would make an entry a second copy of another: compared on the composed configs, not the overrides."""
    configs = {}
    for entry in bench.ENTRIES:
        if entry.kind == "retrained":  # the base's recipe, trained per subset
            continue
        config = json.dumps(to_container(compose_config("train", list(entry.overrides))), sort_keys=True)
        assert config not in configs, f"{entry.label!r} trains {configs.get(config)!r}'s config"
        configs[config] = entry.label
