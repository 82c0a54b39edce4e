"""benchmarks/mpc_push.py --aggregate: rounds of MPC recording, merging and retraining, on real
recorded push data with a tiny world model."""

from __future__ import annotations

import sys

import pytest

from tests.conftest import load_benchmark, push_train_overrides

mpc_push = load_benchmark("mpc_push")


def parse(monkeypatch, *argv: str):
    monkeypatch.setattr(sys, "argv", ["mpc_push.py", *argv])
    return mpc_push.parse_args()


def test_aggregate_records_merges_retrains_and_a_rerun_reuses_it_all(
    recorded_push_root, tmp_path, monkeypatch, capsys
):
    work = tmp_path / "work"
    work.mkdir()
    (work / "push_explore").symlink_to(recorded_push_root)  # the first recording: 6 scripted episodes
    tiny = [
        o
        for o in push_train_overrides(recorded_push_root, tmp_path / "cache", "unused")
        if not o.startswith(("data.root=", "run_dir=", "trainer.total_steps="))  # the script sets them
    ]
    args = parse(
        monkeypatch,
        *("--quick", "--work", str(work), "--world-model-seeds", "0", "--train-steps", "6", "--workers", "1"),
        *("--candidates", "16", "--iterations", "1", "--elites", "4"),
        *("--aggregate", "1", "--aggregate-episodes", "2", "--early-stopping-patience", "0"),
        "--train-override",
        *tiny,
    )
    phases: dict[str, float] = {}
    first = mpc_push.build_world_models(args, phases)
    finals, rows = mpc_push.aggregate_data(args, first, phases)

    assert finals == [work / "world_model_seed0_round1" / "checkpoints"]
    assert [(r["seed"], r["round"]) for r in rows] == [(0, 0), (0, 1)]
    assert (rows[0]["episodes_recorded"], rows[0]["episodes_trained_on"]) == (6, 6)
    assert (rows[1]["episodes_recorded"], rows[1]["episodes_trained_on"]) == (2, 8)
    assert all(0 <= r["recording_success"] <= 100 for r in rows)
    assert rows[0]["steps_trained"] == 6
    assert 1 <= rows[1]["steps_trained"] <= 6  # early stopping may end it sooner
    union = mpc_push.recording_summary(work / "union_seed0_round1")
    first_data = mpc_push.recording_summary(recorded_push_root)
    assert (union["image_size"], union["steps"]) == (first_data["image_size"], first_data["steps"])
    assert "| 0 | 1 | MPC on round 0's world model" in mpc_push.aggregation_table(rows)
    assert {"aggregate seed 0 round 1 record", "aggregate seed 0 round 1 train"} <= set(phases)

    rerun: dict[str, float] = {}
    assert mpc_push.aggregate_data(args, first, rerun) == (finals, rows)
    assert rerun == {}, "a re-run records and trains nothing again"


def test_aggregate_needs_world_models_built_here(monkeypatch, capsys):
    with pytest.raises(SystemExit):
        parse(monkeypatch, "--aggregate", "1", "--checkpoint", "runs/wm0/checkpoints")
    assert "drop --checkpoint" in capsys.readouterr().err
