"""The MPC results table: one line per row, '-' where a row has no seeds or decision time; the
static-object ablation."""

from __future__ import annotations

import torch

from benchmarks.push.closed_loop import over_seeds
from benchmarks.push.mpc_evaluation import StaticObjectModel, evaluate_mpc, results_table
from benchmarks.push.outage_evaluation import Condition
from mmf_rl.rl.cem import SequenceCEMPlanner
from mmf_rl.rl.push_objective import PushObjective


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


def test_the_static_model_is_sure_so_the_uncertainty_penalty_changes_no_plan(
    push_world_model, push_history_env
):
    td = push_history_env.reset()
    static = StaticObjectModel(push_world_model)
    sizes = {"num_candidates": 16, "num_iterations": 2, "num_elites": 4, "seed": 1}
    plans = [
        SequenceCEMPlanner(
            static, PushObjective(uncertainty_weight=weight), push_history_env.action_spec, **sizes
        ).plan(td)
        for weight in (0.0, 1.0)
    ]
    assert torch.equal(plans[0], plans[1])


def test_an_ensemble_plays_as_one_agent_in_both_planners(push_world_model_run, short_episodes):
    checkpoint = push_world_model_run / "checkpoints"
    sizes = {"num_candidates": 8, "num_iterations": 1, "num_elites": 2}
    rows, raw = evaluate_mpc(
        [checkpoint, checkpoint],
        PushObjective(uncertainty_weight=1.0),
        [Condition("all", None, None)],
        sizes,
        episodes=1,
        seed=0,
        stepwise_episodes=1,
        ensemble=True,
    )
    assert rows["mpc all"]["seeds"] == 1 and len(raw["mpc all"]) == 1
    assert rows["mpc static model"]["seeds"] == 1
    assert {"scripted", "random"} <= rows.keys()
    stepwise = {"torchrl CEMPlanner all (first 1, the ensemble)", "mpc all (first 1, the ensemble)"}
    assert stepwise <= rows.keys()
