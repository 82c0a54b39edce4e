"""benchmarks/real_humanoid.py, run as a script: its protocol is mmf_rl.compare's (tests/compare); its
entries, report and resumption are checked on a smoke run on the real G1 recording."""

from __future__ import annotations

import json
import os
import re
import subprocess
from pathlib import Path

import pytest

from tests.conftest import run_bench

REPO = Path(__file__).resolve().parents[2]
G1 = Path(os.environ.get("MMF_RL_SHARED_DATA", REPO.parent / "shared" / "data")) / "g1_pick_bottle_small"
SUMMARY = re.compile(
    r"summary: all sensors paper MSE (\S+) vs best baseline (\S+) \((.+)\): paper/best = (\S+) "
    r"\(target <= 1\.05\); mean degradation without a sensor paper (\S+), best baseline (\S+)"
)
SUBSETS = {
    "all",
    "without_cam_high",
    "without_state",
    "without_action",
    "only_cam_high",
    "only_state",
    "only_action",
}


def humanoid(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return run_bench("humanoid", *args, cwd=cwd)


def test_a_missing_recording_is_a_clear_error(tmp_path):
    run = humanoid("--root", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert run.returncode == 2 and "no LeRobot dataset there (meta/info.json missing)" in run.stderr


@pytest.mark.slow
@pytest.mark.skipif(
    not (G1 / "meta" / "info.json").is_file(),
    reason=f"real G1 recording not found at {G1} (set MMF_RL_SHARED_DATA)",
)
def test_smoke_run_on_the_real_recording_writes_the_results_and_resumes(tmp_path):
    out = tmp_path / "out"
    # The paper model and one baseline: MVAE, whose encoders read a window at once (LF-LSTM and MulT run
    # their ConvNet on each of the 10 frames: several times the cost of scoring every subset).
    argv = ["--steps", "2", "--seeds", "0", "--entries", "paper", "MVAE", "--batch-size", "4"]
    argv += ["--root", str(G1), "--out", str(out)]
    run = humanoid(*argv, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-3000:]
    first = run.stdout.strip().splitlines()[-1]
    assert SUMMARY.fullmatch(first), first
    results = json.loads((out / "results.json").read_text())
    assert (out / "results.md").read_text().strip().splitlines()[-1] == first
    info = results["info"]
    assert info["split"]["test"] and set(results["cells"]) == {"paper", "MVAE"}
    assert results["subsets"][0] == "all" and set(results["subsets"]) == SUBSETS
    for cells in results["cells"].values():
        assert all(c["windows"] == info["test_windows"] for c in cells.values())  # every sensor present
        assert all(c["low"] <= c["mean"] <= c["high"] for c in cells.values())
    assert results["bootstrap"]["unit"] == ("block" if len(info["split"]["test"]) < 10 else "episode")
    assert [r["steps"] for r in results["runs"]["paper"]] == [2]
    assert results["entries"]["paper"]["overrides"][-1] == "model=forecaster"
    # Rerun: both runs are reused, the numbers are the same.
    rerun = humanoid(*argv, cwd=tmp_path)
    assert rerun.stdout.strip().splitlines()[-1] == first
    assert json.loads((out / "results.json").read_text())["info"]["reused"] == 2
    # Another budget in the same --out is refused before any training.
    refused = humanoid(*argv, "--steps", "3", cwd=tmp_path)
    assert refused.returncode == 1 and "would not train (3 steps of batch 4" in refused.stderr
    assert "paper/seed0: 2 steps of batch 4" in refused.stderr
