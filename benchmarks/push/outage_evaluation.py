"""A policy's episode success in the push env with a sensor failing: the conditions the push
experiments compare, a timer of the policy's decisions, and the loop that plays every condition
on the same seeded episodes and outages."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import NamedTuple

from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

from benchmarks.push.closed_loop import SENSORS, play, summarise


class Condition(NamedTuple):
    label: str  # "all", or the failing sensor and how it fails: "no-camera (bursts)"
    sensor: str | None  # the modality that fails; None: every sensor works
    outage: str | None  # how it fails, a key of `benchmarks.push.closed_loop.OUTAGES`


def outage_conditions(outages: list[str]) -> list[Condition]:
    """Every sensor up, then each sensor of `SENSORS` failing each way of ``outages``."""
    return [Condition("all", None, None)] + [
        Condition(f"{name} ({outage})", sensor, outage)
        for outage in outages
        for name, sensor in SENSORS.items()
    ]


class Timed:
    """Wraps a policy; records the seconds of each call."""

    def __init__(self, policy):
        self.policy, self.seconds = policy, []

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        out = self.policy(tensordict)
        self.seconds.append(time.perf_counter() - start)
        return out


def play_conditions(
    make_env: Callable[[Condition], TransformedEnv],
    make_policy: Callable[[TransformedEnv], Callable],
    conditions: list[Condition],
    episodes: int,
    seed: int,
    desc: str,
) -> dict[str, tuple[dict, list[dict]]]:
    """Plays ``episodes`` seeded episodes (`play`) in each condition's env, with the policy made for
    that env. Returns, per condition label, the `summarise` row (with the median decision time
    when the policy is `Timed`) and the episodes; ``desc`` prefixes the label on the progress bar."""
    played = {}
    for condition in conditions:
        env = make_env(condition)
        try:
            policy = make_policy(env)
            results = play(env, policy, episodes, seed, f"{desc}{condition.label}")
        finally:
            env.close()
        seconds = policy.seconds if isinstance(policy, Timed) else None
        played[condition.label] = (summarise(results, seconds), results)
    return played


def success_cells(row: dict) -> list[str]:
    """A played row's cells of the push experiments' success tables: episodes, seeds, success %
    (mean), spread (min-max), per seed, final distance (m), steps; ``-`` where the row has no seeds."""
    spread = f"{row['success_min']:.0f}-{row['success_max']:.0f}" if "success_min" in row else "-"
    per_seed = " / ".join(f"{x:.0f}" for x in row["success_per_seed"]) if "success_per_seed" in row else "-"
    distance = f"{row['final_distance_mean']:.3f} ± {row['final_distance_std']:.3f}"
    return [
        str(row["episodes"]),
        str(row.get("seeds", "-")),
        f"{row['success']:.0f}",
        spread,
        per_seed,
        distance,
        f"{row['steps_mean']:.1f}",
    ]
