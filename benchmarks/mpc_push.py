"""MPC with the push world model, robust to sensor outages: success over seeded episodes.

    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --checkpoint runs/world_model/checkpoints \
        [--episodes 50] [--stepwise-episodes 10] [--out runs/bench_mpc]

The world model comes from::

    mmf-rl record --out data/push_explore --episodes 300 --seed 1 --exploration 0.1
    mmf-rl train experiment=world_model

Every policy plays the same seeded episodes of `MultimodalPushTorchEnv` (episode ``i`` is reset
with seed ``seed + i``; success is FetchPush's: the object within 5 cm of the goal, within the
50-step time limit):

* ``mpc all`` / ``mpc no-camera`` / ``mpc no-force``: `SequenceCEMPlanner` on the world model
  with `PushObjective`; the camera or the force sensor is off for the whole episode
  (`ModalityDropout`, ``outage="episode"``, probability 1), so the world model plans from the
  remaining sensors;
* ``mpc static model``: the same planner and objective with a "world model" that forecasts no
  object motion (all sensors): what the objective's kinematic approach term achieves alone,
  i.e. how much of the success the learned dynamics earn;
* ``scripted``: the pusher that recorded the training data (`ScriptedPusher`, without
  exploration), a strong hand-written controller with full state;
* ``random``: uniform random actions.

Step-wise vs vectorised planning (the design choice of issue #7): the first
``--stepwise-episodes`` episodes are also played with torchrl's `CEMPlanner` rolling out
`ForecasterWorldModelEnv` step by step, with the same candidates, iterations and elites; the
table gives both decision times (measured in the same run) and both success rates on those
episodes.

Ends with ``summary: success all A%, no-camera B%, no-force C%, scripted S%, random R%``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules.planners import CEMPlanner

from mmf_rl import keys
from mmf_rl.envs import ModalityDropout, MultimodalPushTorchEnv
from mmf_rl.envs.scripted import ScriptedPusher, episode_generator
from mmf_rl.eval.report import write_json, write_text
from mmf_rl.rl import ForecasterWorldModelEnv, ImaginedPlanningPolicy, PushObjective, SequenceCEMPlanner, WorldModel

CONDITIONS = {"all": [], "no-camera": ["image"], "no-force": ["force"]}


class StaticObjectModel(WorldModel):
    """The ablation: forecasts that the object stays where it is, whatever the actions."""

    def __init__(self, world_model: WorldModel):
        self.__dict__.update(world_model.__dict__)

    def forecast(self, tokens, present, valid, actions):
        return torch.zeros(*actions.shape[:2], self.horizon, self.target_dim)


def make_env(world_model: WorldModel, image_size: int, dropped: list[str]) -> TransformedEnv:
    transforms = [ModalityDropout(dropped, outage_prob=1.0, outage="episode")] if dropped else []
    transforms += [world_model.history_window(), InitTracker()]
    return TransformedEnv(MultimodalPushTorchEnv(image_size=image_size), Compose(*transforms))


class Timed:
    """Wraps a policy; records the seconds of each call."""

    def __init__(self, policy):
        self.policy, self.seconds = policy, []

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        out = self.policy(tensordict)
        self.seconds.append(time.perf_counter() - start)
        return out


class ScriptedPolicy:
    """`ScriptedPusher` on the TorchRL env's observation; episode ``i`` draws its style from (seed, i)."""

    def __init__(self, seed: int):
        self.seed, self.episode, self.pusher = seed, -1, ScriptedPusher()

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        if bool(tensordict.get("is_init").any()):
            self.episode += 1
            self.pusher.reset(episode_generator(self.seed, self.episode))
        obs = {"proprio": tensordict.get(keys.obs_key("proprio")).numpy(),
               "object_pose": tensordict.get("object_pose").numpy(), "desired_goal": tensordict.get("goal").numpy()}
        return tensordict.set("action", torch.as_tensor(self.pusher.act(obs), dtype=torch.float32))


class RandomPolicy:
    def __init__(self, seed: int):
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict.set("action", torch.rand(4, generator=self.generator) * 2 - 1)


def play(env: TransformedEnv, policy, episodes: int, seed: int, label: str) -> list[dict]:
    results = []
    for i in range(episodes):
        env.set_seed(seed + i)  # applied at the next reset: the same start for every policy
        rollout = env.rollout(env.base_env._env.spec.max_episode_steps, policy, break_when_any_done=True)
        results.append({"success": bool(rollout.get(("next", "terminated")).any()),
                        "final_distance": float(-rollout.get(("next", "reward"))[-1]), "steps": rollout.shape[0]})
        done = sum(r["success"] for r in results)
        print(f"\r{label}: episode {i + 1}/{episodes}, success so far {done}/{i + 1}", end="", flush=True)
    print()
    return results


def summarise(results: list[dict], seconds: list[float] | None = None) -> dict:
    distances = [r["final_distance"] for r in results]
    row = {"episodes": len(results), "success": 100.0 * sum(r["success"] for r in results) / len(results),
           "final_distance_mean": statistics.mean(distances),
           "final_distance_std": statistics.pstdev(distances),
           "steps_mean": statistics.mean(r["steps"] for r in results)}
    if seconds:
        row["decision_ms"] = 1000 * statistics.median(seconds)
    return row


def table(rows: dict[str, dict]) -> str:
    lines = ["| policy | episodes | success % | final distance (m) | steps | decision (ms, median) |",
             "|---|---|---|---|---|---|"]
    for name, r in rows.items():
        decision = f"{r['decision_ms']:.1f}" if "decision_ms" in r else "-"
        lines.append(f"| {name} | {r['episodes']} | {r['success']:.0f} | {r['final_distance_mean']:.3f} ± "
                     f"{r['final_distance_std']:.3f} | {r['steps_mean']:.1f} | {decision} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", default="runs/world_model/checkpoints")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--stepwise-episodes", type=int, default=10,
                        help="episodes also played with torchrl's CEMPlanner (0: skip)")
    parser.add_argument("--seed", type=int, default=1000, help="episode i is reset with seed + i")
    parser.add_argument("--candidates", type=int, default=128)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--elites", type=int, default=16)
    parser.add_argument("--reach-weight", type=float, default=0.5)
    parser.add_argument("--out", default="runs/bench_mpc")
    args = parser.parse_args()
    torch.set_num_threads(2)

    started = time.perf_counter()
    world_model = WorldModel.from_checkpoint(args.checkpoint)
    image_size = world_model.model.modalities[[s.name for s in world_model.model.modalities].index("image")].shape[-1]
    objective = PushObjective(reach_weight=args.reach_weight)
    sizes = {"num_candidates": args.candidates, "num_iterations": args.iterations, "num_elites": args.elites}
    rows, raw = {}, {}
    for name, dropped in CONDITIONS.items():
        env = make_env(world_model, image_size, dropped)
        try:
            planner = Timed(SequenceCEMPlanner(world_model, objective, env.action_spec, seed=args.seed, **sizes))
            raw[f"mpc {name}"] = play(env, planner, args.episodes, args.seed, f"mpc {name}")
            rows[f"mpc {name}"] = summarise(raw[f"mpc {name}"], planner.seconds)
        finally:
            env.close()
    env = make_env(world_model, image_size, [])
    try:
        static = SequenceCEMPlanner(StaticObjectModel(world_model), objective, env.action_spec, seed=args.seed, **sizes)
        for name, policy in [("mpc static model", static), ("scripted", ScriptedPolicy(args.seed)),
                             ("random", RandomPolicy(args.seed))]:
            raw[name] = play(env, policy, args.episodes, args.seed, name)
            rows[name] = summarise(raw[name])
        if args.stepwise_episodes:
            n = min(args.stepwise_episodes, args.episodes)
            world_model_env = ForecasterWorldModelEnv(world_model, objective, env.action_spec, env.observation_spec)
            cem = CEMPlanner(world_model_env, planning_horizon=world_model.action_steps, optim_steps=args.iterations,
                             num_candidates=args.candidates, top_k=args.elites)
            torch.manual_seed(args.seed)
            stepwise = Timed(ImaginedPlanningPolicy(cem, world_model_env))
            raw["torchrl CEMPlanner all"] = play(env, stepwise, n, args.seed, "torchrl CEMPlanner all")
            rows[f"torchrl CEMPlanner all (first {n})"] = summarise(raw["torchrl CEMPlanner all"], stepwise.seconds)
            rows[f"mpc all (first {n})"] = summarise(raw["mpc all"][:n], None)
    finally:
        env.close()

    minutes = (time.perf_counter() - started) / 60
    command = ("benchmarks/mpc_push.py " + " ".join(f"--{k.replace('_', '-')} {v}" for k, v in vars(args).items()))
    text = (f"# MPC on the multimodal push task\n\n`{command}` — {minutes:.1f} min on {torch.get_num_threads()} "
            f"threads\n\nworld model: `{args.checkpoint}`; CEM {args.candidates} candidates × {args.iterations} "
            f"iterations, {args.elites} elites, {world_model.action_steps}-step sequences\n\n{table(rows)}\n")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "results.md", text)
    write_json(out / "results.json", {"rows": rows, "episodes": raw, "args": vars(args)})
    print(text)
    print(f"summary: success all {rows['mpc all']['success']:.0f}%, no-camera {rows['mpc no-camera']['success']:.0f}%, "
          f"no-force {rows['mpc no-force']['success']:.0f}%, scripted {rows['scripted']['success']:.0f}%, "
          f"random {rows['random']['success']:.0f}%")


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
