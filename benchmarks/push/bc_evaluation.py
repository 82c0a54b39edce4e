"""Behaviour-cloning policies with and without the forecaster's forecast, in closed loop under
sensor outages: every policy in every condition on the same seeded episodes and outages, the
scripted pusher for reference, and the tables and summary that compare the two variants (a
variant not played shows as ``-``)."""

from __future__ import annotations

import math
import statistics

import torch
from torchrl.envs import TransformedEnv

from benchmarks.push.closed_loop import ScriptedPolicy, camera_size, over_seeds, play, push_env, summarise
from benchmarks.push.outage_evaluation import Condition, play_conditions, success_cells
from mmf_rl.rl.bc import BCPolicy
from mmf_rl.rl.latched_forecast import LatchedForecastTransform
from mmf_rl.rl.transforms import ForecastTransform

VARIANTS = ("without", "with")  # forecasts


def bc_env(
    policy: BCPolicy | None, forecaster: tuple, image_size: int, condition: Condition, seed: int
) -> TransformedEnv:
    """The push env in ``condition``, then what ``policy`` reads (none: the raw observation, for
    the scripted pusher; the latched forecast for a policy trained on it, ``latched_forecast``).
    ``forecaster``: `mmf_rl.models.loading.load_trained_model`'s triple."""
    readers = []
    if policy is not None:
        reads = policy.config.forecast_shape is not None
        forecast = served_forecast(forecaster, policy.config.latched_forecast) if reads else None
        readers = policy.transforms(forecast)
    return push_env(image_size, condition.sensor, condition.outage, seed, readers)


def served_forecast(forecaster: tuple, latched_rule: str | None) -> ForecastTransform:
    """The forecast transform a policy that reads forecasts reads, in the forecaster's normalised
    frame: the `LatchedForecastTransform` of ``latched_rule``, or (``None``) the fresh forecast.
    ``forecaster``: `mmf_rl.models.loading.load_trained_model`'s triple."""
    model, stats, data_config = forecaster
    if latched_rule is None:
        return ForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    return LatchedForecastTransform.for_trained(
        model, stats, data_config, rule=latched_rule, denormalize=False
    )


@torch.no_grad()
def evaluate_bc(
    policies: dict[str, list[BCPolicy]],
    bc_seeds: list[int],
    forecaster: tuple,
    conditions: list[Condition],
    episodes: int,
    seed: int,
) -> tuple[dict[str, dict], dict[str, list]]:
    """Every policy of each variant played (one per BC seed) in every condition, then the scripted
    pusher with all sensors. Returns the rows (``"BC <variant> forecasts | <condition>"``: mean and spread
    over the BC seeds, `over_seeds`; ``"scripted | all"``) and the episodes of each row."""
    model = forecaster[0]
    image_size = camera_size(model.config.modalities)
    per_seed: dict[str, list[dict]] = {}
    raw: dict[str, list] = {}
    for variant, trained in policies.items():
        for bc_seed, policy in zip(bc_seeds, trained, strict=True):
            played = play_conditions(
                lambda condition, p=policy: bc_env(p, forecaster, image_size, condition, seed),
                lambda env, p=policy: p.eval(),
                conditions,
                episodes,
                seed,
                f"[seed {bc_seed}] BC {variant} forecasts | ",
            )
            for label, (row, results) in played.items():
                per_seed.setdefault(f"BC {variant} forecasts | {label}", []).append(row)
                raw.setdefault(f"BC {variant} forecasts | {label}", []).append(results)
    env = bc_env(None, forecaster, image_size, Condition("all", None, None), seed)
    try:
        raw["scripted | all"] = play(env, ScriptedPolicy(seed), episodes, seed, "scripted")
    finally:
        env.close()
    rows = {name: over_seeds(r) for name, r in per_seed.items()}
    return rows | {"scripted | all": summarise(raw["scripted | all"])}, raw


def success(rows: dict[str, dict], variant: str, label: str) -> float:
    """The row's success %; NaN for a variant not played."""
    row = rows.get(f"BC {variant} forecasts | {label}")
    return math.nan if row is None else row["success"]


def figure(value: float, unit: str = "") -> str:
    """A rounded figure of a table or the summary; ``-`` for a variant not played (NaN)."""
    return "-" if math.isnan(value) else f"{value:.0f}{unit}"


def camera_loss(rows: dict[str, dict], outages: list[str]) -> dict[str, list[float]]:
    """Per outage type, the success points each variant (`VARIANTS` order) loses when the camera
    fails that way, against all sensors up."""
    return {
        outage: [success(rows, v, "all") - success(rows, v, f"no-camera ({outage})") for v in VARIANTS]
        for outage in outages
    }


def camera_target_met(loss: dict[str, list[float]]) -> dict[str, bool]:
    """Per outage type: does the policy with forecasts lose at most half what the one without loses?
    Judged per type: a camera off for the whole episode leaves no sensor that locates the object
    (the observation has no object pose), unlike bursts and a camera that dies mid-episode, which a
    forecaster might bridge."""
    return {outage: lost[1] <= lost[0] / 2 for outage, lost in loss.items()}


def summary_line(rows: dict[str, dict], outages: list[str]) -> str:
    """``summary: BC success all A%/A2%, ...``: success without/with forecasts for the first outage
    type, the camera loss for each, and for how many the target is met."""
    first = outages[0]
    loss = camera_loss(rows, outages)
    met = camera_target_met(loss)

    def pair(label: str) -> str:
        return f"{figure(success(rows, 'without', label), '%')}/{figure(success(rows, 'with', label), '%')}"

    return (
        f"summary: BC success all {pair('all')}, no-camera {pair(f'no-camera ({first})')}, "
        f"no-force {pair(f'no-force ({first})')} (without/with forecasts); camera loss without/with "
        "forecasts "
        + ", ".join(f"{outage} {figure(lost[0])}/{figure(lost[1])} pts" for outage, lost in loss.items())
        + f" (target with <= without/2: met for {sum(met.values())} of {len(met)} outage types)"
    )


def success_table(rows: dict[str, dict]) -> str:
    lines = [
        "| policy | condition | episodes | seeds | success % (mean) | spread (min-max) | per BC seed | "
        "final distance (m) | steps |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        policy, condition = name.split(" | ")
        lines.append("| " + " | ".join([policy, condition, *success_cells(r)]) + " |")
    return "\n".join(lines)


def loss_table(rows: dict[str, dict], conditions: list[Condition]) -> str:
    """Success lost by each variant in each condition but the first (all sensors)."""
    lines = [
        "| condition | success lost without forecasts (pts) | success lost with forecasts (pts) |",
        "|---|---|---|",
    ]
    for condition in conditions[1:]:
        lost = [success(rows, v, "all") - success(rows, v, condition.label) for v in VARIANTS]
        lines.append(f"| {condition.label} | {figure(lost[0])} | {figure(lost[1])} |")
    return "\n".join(lines)


def validation_table(errors: dict[str, list[dict]]) -> str:
    """The offline errors of `mmf_rl.rl.validation_errors`, per variant, mean over BC seeds."""
    if not all(errors.values()):
        return "(no validation episodes)"
    names = list(next(iter(errors.values()))[0])
    lines = [
        "| policy | " + " | ".join(f"val {n}" for n in names) + " |",
        "|---|" + "---|" * len(names),
    ]
    for variant, per_seed in errors.items():
        means = [statistics.mean(e[n] for e in per_seed) for n in names]
        lines.append(f"| BC {variant} forecasts | " + " | ".join(f"{m:.4f}" for m in means) + " |")
    return "\n".join(lines)
