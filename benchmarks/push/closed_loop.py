"""Closed-loop evaluation on the push env: seeded episodes under seeded sensor outages.

Shared by the benchmarks that act in `MultimodalPushTorchEnv` (``benchmarks/mpc_push.py``,
``benchmarks/bc_push.py``): the outage types, the episode loop and its summaries, and the two
reference policies (the scripted pusher that recorded the data, uniform random actions).
"""

from __future__ import annotations

import statistics

import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, InitTracker, Transform, TransformedEnv
from tqdm.auto import tqdm

from mmf_rl import keys
from mmf_rl.envs.modality_dropout import ModalityDropout, UniformBursts
from mmf_rl.envs.scripted import ScriptedPusher, episode_generator
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE, MultimodalPushTorchEnv

# The sensor each outage condition removes.
SENSORS = {"no-camera": "image", "no-force": "force"}
# `ModalityDropout` arguments of each way a sensor fails: ``episode``: off for the whole episode;
# ``bursts``: outages of 2-8 steps starting with probability 0.2 at each step it is up (absent
# about half the time); ``dies``: works for 1-49 steps (uniform), then is off until the episode ends.
OUTAGES = {
    "episode": {"outage": "episode", "outage_prob": 1.0},
    "bursts": {"outage": "bursts", "outage_prob": 0.2, "bursts": UniformBursts(2, 8)},
    "dies": {"outage": "dies", "outage_prob": 1.0, "dies_after": UniformBursts(1, 49)},
}


def camera_size(modalities: list[keys.ModalitySpec]) -> int:
    """The side of the square camera frames a push model was trained on: the size `push_env` renders
    for it."""
    return next(s for s in modalities if s.name == "image").shape[-1]


def sensor_outage(sensor: str, outage: str, seed: int) -> ModalityDropout:
    """``sensor`` failing the ``outage`` way of `OUTAGES`, seeded: the push experiments' outage
    process (in the env, and replayed on recordings to train on: `benchmarks.push.replayed_outages`)."""
    return ModalityDropout([sensor], seed=seed, **OUTAGES[outage])


def push_env(
    image_size: int, sensor: str | None, outage: str | None, seed: int, readers: list[Transform]
) -> TransformedEnv:
    """The push env with ``sensor`` failing the ``outage`` way (seeded), then the transforms a
    policy reads through (``readers``), then an `InitTracker` (the reference policies need it)
    unless ``readers`` have one."""
    failing = [sensor_outage(sensor, outage, seed)] if sensor else []
    tracked = any(isinstance(t, InitTracker) for t in readers)
    return TransformedEnv(
        MultimodalPushTorchEnv(image_size=image_size),
        Compose(*failing, *readers, *([] if tracked else [InitTracker()])),
    )


class ScriptedPolicy:
    """`ScriptedPusher` (or ``pusher``, e.g. a `MarkovPusher`) on the TorchRL env's observation (full
    state: it reads the object's pose); episode ``i`` resets it with the generator of (seed, i), from
    which the scripted pusher draws its style. The env needs an `InitTracker`."""

    def __init__(self, seed: int, pusher: ScriptedPusher | None = None):
        self.seed, self.episode = seed, -1
        self.pusher = ScriptedPusher() if pusher is None else pusher

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        if bool(tensordict.get("is_init").any()):
            self.episode += 1
            self.pusher.reset(episode_generator(self.seed, self.episode))
        obs = {
            "proprio": tensordict.get(keys.obs_key("proprio")).numpy(),
            "object_pose": tensordict.get(OBJECT_POSE).numpy(),
            "desired_goal": tensordict.get(GOAL).numpy(),
        }
        return tensordict.set("action", torch.as_tensor(self.pusher.act(obs), dtype=torch.float32))


class RandomPolicy:
    """Uniform random actions in the push env's box ``[-1, 1]^4``, from a generator seeded once."""

    def __init__(self, seed: int):
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict.set("action", torch.rand(4, generator=self.generator) * 2 - 1)


def episode_steps(env: TransformedEnv) -> int:
    """The push env's time limit (the registered one)."""
    return env.base_env._env.spec.max_episode_steps


def episode_result(rollout: TensorDictBase) -> dict:
    """One played episode: success (FetchPush's, within the time limit), final object-goal distance,
    steps."""
    return {
        "success": bool(rollout.get(("next", "terminated")).any()),
        "final_distance": float(-rollout.get(("next", "reward"))[-1]),
        "steps": rollout.shape[0],
    }


def play(env: TransformedEnv, policy, episodes: int, seed: int, label: str) -> list[dict]:
    """``episodes`` episodes of ``policy`` in ``env`` (episode ``i`` reset with seed ``seed + i``):
    per episode, `episode_result`."""
    results = []
    bar = tqdm(range(episodes), desc=label, unit="episode", dynamic_ncols=True)
    for i in bar:
        env.set_seed(seed + i)  # applied at the next reset: the same start for every policy
        rollout = env.rollout(episode_steps(env), policy, break_when_any_done=True)
        results.append(episode_result(rollout))
        bar.set_postfix(success=f"{sum(r['success'] for r in results)}/{i + 1}")
    return results


def summarise(results: list[dict], seconds: list[float] | None = None) -> dict:
    """One row from the episodes of `play`: success %, final distance (mean, std), mean steps, and
    the median decision time when ``seconds`` (per policy call) are given."""
    distances = [r["final_distance"] for r in results]
    row = {
        "episodes": len(results),
        "success": 100.0 * sum(r["success"] for r in results) / len(results),
        "final_distance_mean": statistics.mean(distances),
        "final_distance_std": statistics.pstdev(distances),
        "steps_mean": statistics.mean(r["steps"] for r in results),
    }
    if seconds:
        row["decision_ms"] = 1000 * statistics.median(seconds)
    return row


def over_seeds(per_seed: list[dict]) -> dict:
    """One row from the rows of several training seeds: mean success with its spread."""
    successes = [r["success"] for r in per_seed]
    row = {
        "episodes": per_seed[0]["episodes"],
        "seeds": len(per_seed),
        "success": statistics.mean(successes),
        "success_min": min(successes),
        "success_max": max(successes),
        "success_per_seed": successes,
        "final_distance_mean": statistics.mean(r["final_distance_mean"] for r in per_seed),
        "final_distance_std": statistics.mean(r["final_distance_std"] for r in per_seed),
        "steps_mean": statistics.mean(r["steps_mean"] for r in per_seed),
    }
    if "decision_ms" in per_seed[0]:
        row["decision_ms"] = statistics.median(r["decision_ms"] for r in per_seed)
    return row
