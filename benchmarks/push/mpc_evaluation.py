"""MPC with push world models under sensor outages: `SequenceCEMPlanner` with `PushObjective` on
each world model (or on their `EnsembleWorldModel`) in every outage condition, the same planner on
a world model that forecasts no object motion, and the references (the scripted pusher, random
actions, torchrl's step-wise `CEMPlanner`), all on the same seeded episodes; the results table."""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torchrl.envs import TransformedEnv
from torchrl.modules.planners import CEMPlanner

from benchmarks.push.closed_loop import (
    RandomPolicy,
    ScriptedPolicy,
    camera_size,
    over_seeds,
    play,
    push_env,
    summarise,
)
from benchmarks.push.outage_evaluation import Condition, Timed, play_conditions, success_cells
from mmf_rl.rl.cem import SequenceCEMPlanner
from mmf_rl.rl.ensemble_world_model import EnsembleWorldModel
from mmf_rl.rl.push_objective import PushObjective
from mmf_rl.rl.world_model import WorldModel
from mmf_rl.rl.world_model_env import ForecasterWorldModelEnv, ImaginedPlanningPolicy

PlannedWorldModel = WorldModel | EnsembleWorldModel


class StaticObjectModel(WorldModel):
    """The ablation: forecasts that the object stays where it is, whatever the actions, and is sure
    of it (no spread, so an uncertainty penalty costs every plan the same: nothing)."""

    def __init__(self, world_model: WorldModel):
        # The loaded world model's state as is (its window, action frame and encoder): nothing is
        # loaded or checked again, and only the forecasts change.
        self.__dict__.update(world_model.__dict__)

    def forecast(self, tokens, present, valid, actions):
        return torch.zeros(*actions.shape[:2], self.horizon, self.target_dim)

    def forecast_distribution(self, tokens, present, valid, actions):
        still = self.forecast(tokens, present, valid, actions)
        return still, torch.zeros_like(still)


def cem_policy(world_model: PlannedWorldModel, objective: PushObjective, sizes: dict[str, int], seed: int):
    """A maker of the `Timed` `SequenceCEMPlanner` for an env (its action spec)."""
    return lambda env: Timed(SequenceCEMPlanner(world_model, objective, env.action_spec, seed=seed, **sizes))


def planning_env(world_model: PlannedWorldModel, condition: Condition, seed: int) -> TransformedEnv:
    """The real push env in ``condition``, with the history window the world model reads (not the
    imagined `ForecasterWorldModelEnv`)."""
    return push_env(
        camera_size(world_model.modalities),
        condition.sensor,
        condition.outage,
        seed,
        [world_model.history_window()],
    )


def world_models(checkpoints: list, ensemble: bool) -> Iterator[tuple[str, PlannedWorldModel]]:
    """The world models played, loaded one at a time with their progress tag: one per checkpoint,
    or (``ensemble``) their `EnsembleWorldModel` alone."""
    if ensemble:
        yield f"[ensemble of {len(checkpoints)}]", EnsembleWorldModel.from_checkpoints(checkpoints)
        return
    for index, checkpoint in enumerate(checkpoints):
        yield f"[world model {index + 1}/{len(checkpoints)}]", WorldModel.from_checkpoint(checkpoint)


def evaluate_mpc(
    checkpoints: list,
    objective: PushObjective,
    conditions: list[Condition],
    sizes: dict[str, int],
    episodes: int,
    seed: int,
    stepwise_episodes: int = 0,
    ensemble: bool = False,
) -> tuple[dict[str, dict], dict[str, list]]:
    """Every world model's MPC in every condition and with the static model, then (once) the
    references. ``sizes``: the CEM's ``num_candidates``, ``num_iterations``, ``num_elites``.
    ``ensemble``: one MPC agent plans with the `EnsembleWorldModel` of all ``checkpoints`` (one
    "seed" in the rows; the static model on its first member: it ignores the forecaster).
    Returns the rows (an MPC row: mean and spread over the world models, `over_seeds`) and the
    episodes of each row (MPC: one list per world model)."""
    per_seed: dict[str, list[dict]] = {}
    raw: dict[str, list] = {}
    references: dict[str, dict] = {}
    for index, (tag, world_model) in enumerate(world_models(checkpoints, ensemble)):
        played = play_conditions(
            lambda condition, model=world_model: planning_env(model, condition, seed),
            cem_policy(world_model, objective, sizes, seed),
            conditions,
            episodes,
            seed,
            f"{tag} mpc ",
        )
        # The static model and the references play in one env with every sensor up.
        env = planning_env(world_model, Condition("all", None, None), seed)
        try:
            single = world_model.members[0] if ensemble else world_model
            static = cem_policy(StaticObjectModel(single), objective, sizes, seed)(env)
            results = play(env, static, episodes, seed, f"{tag} mpc static model")
            played["static model"] = (summarise(results, static.seconds), results)
            for label, (row, results) in played.items():
                per_seed.setdefault(f"mpc {label}", []).append(row)
                raw.setdefault(f"mpc {label}", []).append(results)
            if index == 0:  # the references do not depend on the world model: played once
                references = play_references(env, episodes, seed, raw)
                if stepwise_episodes:
                    n = min(stepwise_episodes, episodes)
                    which = "the ensemble" if ensemble else "world model 1"
                    references |= play_stepwise(env, world_model, objective, sizes, n, seed, raw, which)
        finally:
            env.close()
    return {name: over_seeds(rows) for name, rows in per_seed.items()} | references, raw


def play_references(env: TransformedEnv, episodes: int, seed: int, raw: dict) -> dict[str, dict]:
    """The scripted pusher and random actions; their episodes go to ``raw``."""
    rows = {}
    for name, policy in [("scripted", ScriptedPolicy(seed)), ("random", RandomPolicy(seed))]:
        raw[name] = play(env, policy, episodes, seed, name)
        rows[name] = summarise(raw[name])
    return rows


def play_stepwise(
    env: TransformedEnv,
    world_model: PlannedWorldModel,
    objective: PushObjective,
    sizes: dict[str, int],
    n: int,
    seed: int,
    raw: dict,
    which: str,
) -> dict[str, dict]:
    """torchrl's `CEMPlanner` rolling out `ForecasterWorldModelEnv` step by step with the same
    candidates, iterations and elites, on the first ``n`` episodes, beside the vectorised MPC's
    row on the same episodes (``raw["mpc all"][0]``: the first world model's, or the ensemble's);
    ``which`` names that world model in the rows."""
    imagined = ForecasterWorldModelEnv(world_model, objective, env.action_spec, env.observation_spec)
    cem = CEMPlanner(
        imagined,
        planning_horizon=world_model.action_steps,
        optim_steps=sizes["num_iterations"],
        num_candidates=sizes["num_candidates"],
        top_k=sizes["num_elites"],
    )
    torch.manual_seed(seed)
    stepwise = Timed(ImaginedPlanningPolicy(cem, imagined))
    raw["torchrl CEMPlanner all"] = play(env, stepwise, n, seed, "torchrl CEMPlanner all")
    return {
        f"torchrl CEMPlanner all (first {n}, {which})": summarise(
            raw["torchrl CEMPlanner all"], stepwise.seconds
        ),
        f"mpc all (first {n}, {which})": summarise(raw["mpc all"][0][:n]),
    }


def results_table(rows: dict[str, dict]) -> str:
    """One line per row: success (mean, spread and per world-model seed), final distance, steps and
    the median decision time."""
    lines = [
        "| policy | episodes | seeds | success % (mean) | spread (min-max) | per world-model seed | "
        "final distance (m) | steps | decision (ms/step, median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        decision = f"{r['decision_ms']:.1f}" if "decision_ms" in r else "-"
        lines.append("| " + " | ".join([name, *success_cells(r), decision]) + " |")
    return "\n".join(lines)
