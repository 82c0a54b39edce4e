"""The MPC results table: one line per row, '-' where a row has no seeds or decision time."""

from __future__ import annotations

from mmf_rl.rl.closed_loop import over_seeds
from mmf_rl.rl.mpc_evaluation import results_table


def row(success: float, decision_ms: float | None = None) -> dict:
    r = {
        "episodes": 2,
        "success": success,
        "final_distance_mean": 0.1,
        "final_distance_std": 0.02,
        "steps_mean": 40,
    }
    return r | ({"decision_ms": decision_ms} if decision_ms is not None else {})


def test_results_table_gives_the_spread_over_seeds_and_dashes_for_references():
    rows = {"mpc all": over_seeds([row(50.0, 3.0), row(100.0, 5.0)]), "scripted": row(100.0)}
    lines = results_table(rows).splitlines()
    assert len(lines) == 4
    assert lines[2] == "| mpc all | 2 | 2 | 75 | 50-100 | 50 / 100 | 0.100 ± 0.020 | 40.0 | 4.0 |"
    assert lines[3] == "| scripted | 2 | - | 100 | - | - | 0.100 ± 0.020 | 40.0 | - |"
