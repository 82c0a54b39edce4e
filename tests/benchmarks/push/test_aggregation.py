"""Data aggregation: rounds of MPC recording, merging and retraining, on real recorded push data
with a tiny world model."""

from __future__ import annotations

import argparse

import pytest

from benchmarks.push.aggregation import (
    AggregationConfig,
    add_aggregation_arguments,
    aggregate_data,
    aggregation_table,
    check_aggregation_arguments,
    recording_summary,
    train_world_model,
)
from tests.conftest import push_train_overrides


def test_aggregate_records_merges_retrains_and_a_rerun_reuses_it_all(
    recorded_push_root, push_cache_dir, tmp_path
):
    work = tmp_path / "work"
    work.mkdir()
    (work / "push_explore").symlink_to(recorded_push_root)  # the first recording: 6 scripted episodes
    tiny = [
        o
        for o in push_train_overrides(recorded_push_root, push_cache_dir, "unused")
        if not o.startswith(("data.root=", "run_dir="))  # train_world_model sets them
    ]
    config = AggregationConfig(
        work=work,
        seeds=[0],
        rounds=1,
        episodes=2,
        early_stopping_patience=0,
        workers=1,
        agent={"num_candidates": 16, "num_iterations": 1, "num_elites": 4},
        train_overrides=tiny,
    )
    first = train_world_model(work / "world_model_seed0", work / "push_explore", 0, tiny)
    phases: dict[str, float] = {}
    finals, rows = aggregate_data(config, [first], phases)

    assert finals == [work / "world_model_seed0_round1" / "checkpoints"]
    assert [(r["seed"], r["round"]) for r in rows] == [(0, 0), (0, 1)]
    assert (rows[0]["episodes_recorded"], rows[0]["episodes_trained_on"]) == (6, 6)
    assert (rows[1]["episodes_recorded"], rows[1]["episodes_trained_on"]) == (2, 8)
    assert all(0 <= r["recording_success"] <= 100 for r in rows)
    assert rows[0]["steps_trained"] == 6
    assert 1 <= rows[1]["steps_trained"] <= 6  # early stopping may end it sooner
    union = recording_summary(work / "union_seed0_round1")
    first_data = recording_summary(recorded_push_root)
    assert (union["image_size"], union["steps"]) == (first_data["image_size"], first_data["steps"])
    assert "| 0 | 1 | MPC on round 0's world model" in aggregation_table(rows)
    assert set(phases) == {"aggregate seed 0 round 1 record", "aggregate seed 0 round 1 train"}

    rerun: dict[str, float] = {}
    assert aggregate_data(config, [first], rerun) == (finals, rows)
    assert rerun == {}, "a re-run records and trains nothing again"


def test_aggregation_needs_world_models_built_here(capsys):
    parser = argparse.ArgumentParser()
    add_aggregation_arguments(parser)
    args = parser.parse_args(["--aggregate", "1"])
    check_aggregation_arguments(parser, args, world_models_given=False)
    with pytest.raises(SystemExit):
        check_aggregation_arguments(parser, args, world_models_given=True)
    assert "drop --checkpoint" in capsys.readouterr().err
