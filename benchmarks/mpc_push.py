"""MPC with the push world model, robust to sensor outages: success over seeded episodes and
world-model seeds.

    # quick: builds what it lacks (records, trains 2 world models with a small budget), then plays
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --quick
    # full: the committed budget (experiment=world_model), 50 episodes, every outage type
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py
    # given world models (one per training seed), nothing built
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py \
        --checkpoint runs/wm0/checkpoints runs/wm1/checkpoints
    # PETS-style data aggregation: 2 rounds of 100 MPC episodes each, retraining on the union
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --quick --aggregate 2 --aggregate-episodes 100

What it builds when absent (under ``--work``; a re-run reuses the recording and resumes or skips
the trainings): the exploration recording (`mmf_rl.record`, ``--record-episodes`` episodes, seed
1, exploration 0.1, as ``mmf-rl record --out data/push_explore --episodes 300 --seed 1
--exploration 0.1``) and one world model per ``--world-model-seeds`` (``mmf-rl train
experiment=world_model trainer.seed=S``, ``--train-steps`` steps).

=========================  ======  =====
budget                     quick   full
=========================  ======  =====
recorded episodes          300     300
training steps per seed    1500    4000 (configs/experiment/world_model.yaml)
world-model seeds          0 1     0 1
episodes per condition     20      50
outage types               episode episode bursts dies
step-wise CEMPlanner eps.  0       10
aggregation rounds         0       0     (--aggregate; 100 episodes each, --aggregate-episodes)
=========================  ======  =====

Data aggregation (``--aggregate ROUNDS``, PETS-style; issue #15): after the first world models
are trained, each round records ``--aggregate-episodes`` episodes with the current MPC agent
(`mmf_rl.rl.PushMPCAgent`: the planner and objective below, all sensors up) plus the recorder's
random-move bursts (``--aggregate-exploration``, the meaning of ``mmf-rl record
--exploration``), merges them with that world model's training data (lerobot's
`aggregate_datasets`, `mmf_rl.record.merge_recordings`) and trains the next world model on the
union, with the same seed and step budget, and early stopping on the validation MSE
(``--early-stopping-patience`` evaluations without improvement; the trainer's own
``trainer.early_stopping_patience``, which keeps the weights it stopped with, not the best
evaluation's). The world models of the last round are the ones played.
Each world-model seed aggregates its own data (its agent records, its union trains it): the seeds
stay independent replicates of the whole procedure, so their spread includes the data's. A
retraining starts from scratch by default: the union's normalisation statistics differ from
the last round's, and a model trained by the same recipe on more data is what the rounds are
meant to measure; ``--aggregate-warm-start`` starts from the last round's weights instead
(``init_from``: new optimizer and schedule, the union's statistics), which converges in fewer
steps with early stopping. Round ``r`` records with seed ``r + 1`` (the first recording's is 1),
so its episodes start elsewhere, with the first recording's image size and episode length.
``results.md`` lists every round: episodes recorded, episodes
trained on, the recording agent's success (the object within FetchPush's 5 cm of the goal at
some recorded frame, exploration bursts included) and the steps trained.

Run time: the script prints the minutes of each phase (record, each training, play) and the
total, and writes them to ``results.md``; the quick mode is sized to finish within 25 min on 2
CPU cores (measured: 9.7 min on a quiet machine). Full mode: about 2.7 min of recording,
11-13 min per 4000-step world-model training (measured with ``--threads 1`` beside another job,
so upper bounds), and 12.0 min of play for the two world models, the 10 step-wise `CEMPlanner`
episodes included (quiet machine, 2 threads): about 40 min in all.

Every policy plays the same seeded episodes of `MultimodalPushTorchEnv` (episode ``i`` is reset
with seed ``seed + i``; success is FetchPush's: the object within 5 cm of the goal, within the
50-step time limit). The outages are seeded too: every world model meets the same ones.

* ``mpc all`` / ``mpc no-camera (<outage>)`` / ``mpc no-force (<outage>)``: `SequenceCEMPlanner`
  on the world model with `PushObjective`, the camera or the force sensor failing the
  ``--outage`` way (`ModalityDropout`): ``episode``: off for the whole episode; ``bursts``:
  outages of 2-8 steps starting with probability 0.2 at each step it is up (absent about half
  the time); ``dies``: works for 1-49 steps (uniform), then is off until the episode ends. The
  same world model plans from the remaining sensors: no retraining per outage.
* ``mpc static model``: the same planner and objective with a "world model" that forecasts no
  object motion (all sensors): what the objective's kinematic approach term achieves alone.
* ``scripted``: the pusher that recorded the training data (`ScriptedPusher`, without
  exploration), a strong hand-written controller with full state;
* ``random``: uniform random actions.

The order of the MPC conditions flips from one world-model training to the next (issue #15), so
every MPC row is given per world-model seed and as mean with its spread (min-max) over seeds,
beside the median decision time per step (the planner's call, measured in the same run).

Step-wise vs vectorised planning (the design choice of issue #7): the first
``--stepwise-episodes`` episodes are also played with torchrl's `CEMPlanner` rolling out
`ForecasterWorldModelEnv` step by step with the first world model, with the same candidates,
iterations and elites.

Ends with ``summary: success all A%, no-camera B%, no-force C%, scripted S%, random R%`` (MPC:
mean over world-model seeds, the first ``--outage`` type).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv
from torchrl.modules.planners import CEMPlanner

from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.cli import configure_logging
from mmf_rl.eval.report import write_json, write_text
from mmf_rl.rl import (
    ForecasterWorldModelEnv,
    ImaginedPlanningPolicy,
    PushObjective,
    SequenceCEMPlanner,
    WorldModel,
)
from mmf_rl.rl.closed_loop import (
    OUTAGES,
    SENSORS,
    RandomPolicy,
    ScriptedPolicy,
    over_seeds,
    play,
    push_env,
    summarise,
)

FIRST_RECORDING = {"seed": 1, "exploration": 0.1}  # of the data the first world models train on
SUCCESS_DISTANCE = 0.05  # FetchPush's distance_threshold, metres (3-D, object to goal)
BUDGETS = {
    "quick": {
        "record_episodes": 300,
        "train_steps": 1500,
        "episodes": 20,
        "outage": ["episode"],
        "stepwise_episodes": 0,
    },
    "full": {
        "record_episodes": 300,
        "train_steps": None,
        "episodes": 50,
        "outage": list(OUTAGES),
        "stepwise_episodes": 10,
    },
}


class StaticObjectModel(WorldModel):
    """The ablation: forecasts that the object stays where it is, whatever the actions."""

    def __init__(self, world_model: WorldModel):
        self.__dict__.update(world_model.__dict__)

    def forecast(self, tokens, present, valid, actions):
        return torch.zeros(*actions.shape[:2], self.horizon, self.target_dim)


def make_env(
    world_model: WorldModel,
    image_size: int,
    dropped: str | None = None,
    outage: str = "episode",
    seed: int = 0,
) -> TransformedEnv:
    return push_env(image_size, dropped, outage, seed, [world_model.history_window()])


class Timed:
    """Wraps a policy; records the seconds of each call."""

    def __init__(self, policy):
        self.policy, self.seconds = policy, []

    def __call__(self, tensordict: TensorDictBase) -> TensorDictBase:
        start = time.perf_counter()
        out = self.policy(tensordict)
        self.seconds.append(time.perf_counter() - start)
        return out


def table(rows: dict[str, dict]) -> str:
    lines = [
        "| policy | episodes | seeds | success % (mean) | spread (min-max) | per world-model seed | "
        "final distance (m) | steps | decision (ms/step, median) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        decision = f"{r['decision_ms']:.1f}" if "decision_ms" in r else "-"
        seeds = r.get("seeds", "-")
        spread = f"{r['success_min']:.0f}-{r['success_max']:.0f}" if "success_min" in r else "-"
        per_seed = " / ".join(f"{x:.0f}" for x in r["success_per_seed"]) if "success_per_seed" in r else "-"
        lines.append(
            f"| {name} | {r['episodes']} | {seeds} | {r['success']:.0f} | {spread} | {per_seed} | "
            f"{r['final_distance_mean']:.3f} ± {r['final_distance_std']:.3f} | {r['steps_mean']:.1f} | "
            f"{decision} |"
        )
    return "\n".join(lines)


def train_world_model(args, run_dir: Path, data: Path, seed: int, extra: list[str] = ()) -> None:
    """``mmf-rl train experiment=world_model`` on ``data`` into ``run_dir``; resumes an interrupted run."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.trainers.train_command import train

    overrides = [
        "experiment=world_model",
        f"name={run_dir.name}",
        f"run_dir={run_dir}",
        f"data.root={data}",
        f"trainer.seed={seed}",
        "trainer.progress_bar=false",
        *args.train_override,
        *extra,
    ]
    if args.train_steps is not None:
        overrides.append(f"trainer.total_steps={args.train_steps}")
    if list_checkpoints(run_dir / "checkpoints"):
        overrides.append("resume=true")  # finishes an interrupted training; nothing to do if it had ended
    train(compose_config("train", overrides))


def build_world_models(args, phases: dict[str, float]) -> list[Path]:
    """The recording and one world model per seed under ``args.work``, built where absent."""
    from mmf_rl.record import RecordConfig, record

    data = args.work / "push_explore"
    if not (data / "meta" / "info.json").is_file():
        print(f"mpc_push: recording {args.record_episodes} exploration episodes into {data}")
        start = time.perf_counter()
        record(RecordConfig(out=data, episodes=args.record_episodes, workers=args.workers, **FIRST_RECORDING))
        phases["record"] = time.perf_counter() - start
    checkpoints = []
    for seed in args.world_model_seeds:
        run_dir = args.work / f"world_model_seed{seed}"
        start = time.perf_counter()
        train_world_model(args, run_dir, data, seed)
        phases[f"train seed {seed}"] = time.perf_counter() - start
        checkpoints.append(run_dir / "checkpoints")
    return checkpoints


def recording_summary(root: Path) -> dict:
    """A recording's episodes, the per cent of them where the object came within
    `SUCCESS_DISTANCE` of the goal at some frame, its image size and steps per episode."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from mmf_rl.datasets.lerobot_source import load_frame_columns
    from mmf_rl.record import CAMERA_KEY, GOAL_KEY, OBJECT_POSE_KEY, RecordConfig

    meta = LeRobotDatasetMetadata(RecordConfig.repo_id, root=root)
    frames, _, _ = load_frame_columns(meta, [OBJECT_POSE_KEY, GOAL_KEY, "episode_index"])
    reached = np.linalg.norm(frames[OBJECT_POSE_KEY][:, :3] - frames[GOAL_KEY], axis=1) < SUCCESS_DISTANCE
    episodes = np.unique(frames["episode_index"])
    successes = sum(bool(reached[frames["episode_index"] == e].any()) for e in episodes)
    return {
        "episodes": len(episodes),
        "success": 100.0 * successes / len(episodes),
        "image_size": int(meta.features[CAMERA_KEY]["shape"][0]),
        "steps": meta.total_frames // meta.total_episodes,  # every episode of a recording is as long
    }


def trained_steps(checkpoints: Path) -> int:
    return load_checkpoint(checkpoints, with_trainer_state=False).step


def aggregate_data(args, checkpoints: list[Path], phases: dict[str, float]) -> tuple[list[Path], list[dict]]:
    """``args.aggregate`` rounds of PETS-style data aggregation per world-model seed (module
    docstring); returns the last round's world models and one row per seed and round. A re-run
    reuses finished recordings, unions and trainings, and resumes an interrupted training."""
    from mmf_rl.record import RecordConfig, merge_recordings, record
    from mmf_rl.rl import PushMPCAgent
    from mmf_rl.trainers.train_command import PRETRAINED_DIR

    base = args.work / "push_explore"
    first = recording_summary(base)
    rows, finals = [], []
    for seed, checkpoint in zip(args.world_model_seeds, checkpoints, strict=True):
        data = base
        rows.append(
            {
                "seed": seed,
                "round": 0,
                "recorded_by": f"scripted pusher + exploration {FIRST_RECORDING['exploration']}",
                "episodes_recorded": first["episodes"],
                "episodes_trained_on": first["episodes"],
                "recording_success": first["success"],
                "steps_trained": trained_steps(checkpoint),
                "world_model": str(checkpoint),
            }
        )
        for round_ in range(1, args.aggregate + 1):
            tag = f"seed {seed} round {round_}"
            recording = args.work / f"aggregate_seed{seed}_round{round_}"
            if not (recording / "meta" / "info.json").is_file():  # a recording is written atomically
                print(f"mpc_push: [{tag}] recording {args.aggregate_episodes} MPC episodes with {checkpoint}")
                agent = PushMPCAgent(
                    checkpoint,
                    image_size=first["image_size"],
                    num_candidates=args.candidates,
                    num_iterations=args.iterations,
                    num_elites=args.elites,
                    reach_weight=args.reach_weight,
                )
                start = time.perf_counter()
                record(
                    RecordConfig(
                        out=recording,
                        episodes=args.aggregate_episodes,
                        workers=args.workers,
                        seed=FIRST_RECORDING["seed"] + round_,
                        image_size=first["image_size"],  # recorded as the first data, so that both merge
                        steps=first["steps"],
                        exploration=args.aggregate_exploration,
                        policy=agent,
                    )
                )
                phases[f"aggregate {tag} record"] = time.perf_counter() - start
            union = args.work / f"union_seed{seed}_round{round_}"
            if not (union / "meta" / "info.json").is_file():
                merge_recordings([data, recording], union)
            run_dir = args.work / f"world_model_seed{seed}_round{round_}"
            if not (run_dir / PRETRAINED_DIR).is_dir():  # written when a training ends, early or not
                extra = [f"trainer.early_stopping_patience={args.early_stopping_patience}"]
                if args.aggregate_warm_start:
                    extra.append(f"init_from={Path(checkpoint).parent}")
                start = time.perf_counter()
                train_world_model(args, run_dir, union, seed, extra)
                phases[f"aggregate {tag} train"] = time.perf_counter() - start
            recorded = recording_summary(recording)
            data, checkpoint = union, run_dir / "checkpoints"
            rows.append(
                {
                    "seed": seed,
                    "round": round_,
                    "recorded_by": f"MPC on round {round_ - 1}'s world model + exploration "
                    f"{args.aggregate_exploration}",
                    "episodes_recorded": recorded["episodes"],
                    "episodes_trained_on": recording_summary(union)["episodes"],
                    "recording_success": recorded["success"],
                    "steps_trained": trained_steps(checkpoint),
                    "world_model": str(checkpoint),
                }
            )
        finals.append(checkpoint)
    return finals, rows


def aggregation_table(rows: list[dict]) -> str:
    lines = [
        "| world-model seed | round | recorded by | episodes recorded | episodes trained on | "
        "recording success % | steps trained | world model |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['round']} | {r['recorded_by']} | {r['episodes_recorded']} | "
            f"{r['episodes_trained_on']} | {r['recording_success']:.0f} | {r['steps_trained']} | "
            f"`{r['world_model']}` |"
        )
    return "\n".join(lines)


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the small budget (see the table above)")
    parser.add_argument(
        "--checkpoint",
        type=Path,
        nargs="+",
        default=None,
        help="world models to use, one per training seed (default: build them under --work)",
    )
    parser.add_argument(
        "--work",
        type=Path,
        default=None,
        help="where the recording and world models are built (default runs/bench_mpc_{quick,full})",
    )
    parser.add_argument(
        "--world-model-seeds", type=int, nargs="+", default=[0, 1], help="trainer.seed of each"
    )
    parser.add_argument("--record-episodes", type=int, default=None)
    parser.add_argument(
        "--train-steps", type=int, default=None, help="default: quick 1500, full the config's"
    )
    parser.add_argument("--workers", type=int, default=2, help="recording processes")
    parser.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch threads; use 1 on a shared machine (OpenMP threads spin-wait for a thread whose "
        "core is busy: a 2-thread training beside another job ran 13x slower than alone)",
    )
    parser.add_argument(
        "--train-override",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="Hydra overrides added to every world-model training (e.g. model.d_model=64)",
    )
    parser.add_argument(
        "--episodes", type=int, default=None, help="episodes per condition (quick 20, full 50)"
    )
    parser.add_argument(
        "--outage",
        nargs="+",
        choices=list(OUTAGES),
        default=None,
        help="how the sensor fails (quick: episode; full: all); the summary uses the first",
    )
    parser.add_argument(
        "--stepwise-episodes",
        type=int,
        default=None,
        help="episodes also played with torchrl's CEMPlanner (0: skip; quick 0, full 10)",
    )
    parser.add_argument("--seed", type=int, default=1000, help="episode i is reset with seed + i")
    parser.add_argument("--candidates", type=int, default=128)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--elites", type=int, default=16)
    parser.add_argument("--reach-weight", type=float, default=0.5)
    parser.add_argument("--out", type=Path, default=None, help="default runs/bench_mpc_{quick,full}")
    parser.add_argument(
        "--aggregate",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="rounds of data aggregation with the MPC agent before playing (0: none)",
    )
    parser.add_argument("--aggregate-episodes", type=int, default=100, help="episodes recorded per round")
    parser.add_argument(
        "--aggregate-exploration",
        type=float,
        default=0.1,
        help=(
            "per-step probability of a random-move burst while the agent records (mmf-rl record "
            "--exploration)"
        ),
    )
    parser.add_argument(
        "--early-stopping-patience",
        type=int,
        default=2,
        help="retrainings of the aggregation rounds stop after this many evaluations without a better "
        "val/mse",
    )
    parser.add_argument(
        "--aggregate-warm-start",
        action="store_true",
        help="retrain from the last round's weights (init_from) instead of from scratch",
    )
    args = parser.parse_args()
    if args.aggregate < 0 or args.aggregate_episodes < 1 or args.early_stopping_patience < 0:
        parser.error("--aggregate must be >= 0, --aggregate-episodes >= 1, --early-stopping-patience >= 0")
    if args.aggregate and args.checkpoint:
        parser.error(
            "--aggregate retrains on the data the world models were trained on: build them here "
            "(drop --checkpoint)"
        )
    mode = "quick" if args.quick else "full"
    for key, value in BUDGETS[mode].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.work = args.work or Path(f"runs/bench_mpc_{mode}")
    args.out = args.out or args.work
    return args


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    phases: dict[str, float] = {}
    checkpoints = args.checkpoint or build_world_models(args, phases)
    aggregation: list[dict] = []
    if args.aggregate:
        checkpoints, aggregation = aggregate_data(args, checkpoints, phases)

    objective = PushObjective(reach_weight=args.reach_weight)
    sizes = {"num_candidates": args.candidates, "num_iterations": args.iterations, "num_elites": args.elites}
    conditions = [("all", None, args.outage[0])] + [
        (f"{name} ({outage})", sensor, outage) for outage in args.outage for name, sensor in SENSORS.items()
    ]
    per_seed: dict[str, list[dict]] = {}
    raw: dict[str, list] = {}
    play_start = time.perf_counter()
    for index, checkpoint in enumerate(checkpoints):
        world_model = WorldModel.from_checkpoint(checkpoint)
        image_size = next(s for s in world_model.model.modalities if s.name == "image").shape[-1]
        tag = f"[world model {index + 1}/{len(checkpoints)}]"
        for label, sensor, outage in conditions:
            env = make_env(world_model, image_size, sensor, outage, seed=args.seed)
            try:
                planner = Timed(
                    SequenceCEMPlanner(world_model, objective, env.action_spec, seed=args.seed, **sizes)
                )
                results = play(env, planner, args.episodes, args.seed, f"{tag} mpc {label}")
            finally:
                env.close()
            per_seed.setdefault(f"mpc {label}", []).append(summarise(results, planner.seconds))
            raw.setdefault(f"mpc {label}", []).append(results)
        env = make_env(world_model, image_size)
        try:
            static = Timed(
                SequenceCEMPlanner(
                    StaticObjectModel(world_model), objective, env.action_spec, seed=args.seed, **sizes
                )
            )
            results = play(env, static, args.episodes, args.seed, f"{tag} mpc static model")
            per_seed.setdefault("mpc static model", []).append(summarise(results, static.seconds))
            raw.setdefault("mpc static model", []).append(results)
            if index == 0:
                # The baselines do not depend on the world model: played once.
                baselines = {}
                for name, policy in [
                    ("scripted", ScriptedPolicy(args.seed)),
                    ("random", RandomPolicy(args.seed)),
                ]:
                    raw[name] = play(env, policy, args.episodes, args.seed, name)
                    baselines[name] = summarise(raw[name])
                if args.stepwise_episodes:
                    n = min(args.stepwise_episodes, args.episodes)
                    world_model_env = ForecasterWorldModelEnv(
                        world_model, objective, env.action_spec, env.observation_spec
                    )
                    cem = CEMPlanner(
                        world_model_env,
                        planning_horizon=world_model.action_steps,
                        optim_steps=args.iterations,
                        num_candidates=args.candidates,
                        top_k=args.elites,
                    )
                    torch.manual_seed(args.seed)
                    stepwise = Timed(ImaginedPlanningPolicy(cem, world_model_env))
                    raw["torchrl CEMPlanner all"] = play(
                        env, stepwise, n, args.seed, "torchrl CEMPlanner all"
                    )
                    baselines[f"torchrl CEMPlanner all (first {n}, world model 1)"] = summarise(
                        raw["torchrl CEMPlanner all"], stepwise.seconds
                    )
                    baselines[f"mpc all (first {n}, world model 1)"] = summarise(raw["mpc all"][0][:n])
        finally:
            env.close()
    phases["play"] = time.perf_counter() - play_start
    rows = {name: over_seeds(rows) for name, rows in per_seed.items()} | baselines

    minutes = (time.perf_counter() - started) / 60
    timing = ", ".join(f"{name} {seconds / 60:.1f} min" for name, seconds in phases.items())
    command = " ".join(["benchmarks/mpc_push.py", *sys.argv[1:]])
    budget = (
        f"{args.episodes} episodes per condition, outages {' '.join(args.outage)}, "
        f"{len(checkpoints)} world models"
        + (
            ""
            if args.checkpoint
            else f" (seeds {args.world_model_seeds}, "
            f"{args.train_steps or 'the config'} training steps, "
            f"{args.record_episodes} recorded episodes)"
        )
        + (
            f"; {args.aggregate} aggregation rounds of {args.aggregate_episodes} MPC episodes "
            f"(exploration {args.aggregate_exploration}, "
            f"{'warm start' if args.aggregate_warm_start else 'retrained from scratch'}, "
            f"early stopping patience {args.early_stopping_patience})"
            if args.aggregate
            else ""
        )
    )
    text = (
        f"# MPC on the multimodal push task\n\n`{command}` — {minutes:.1f} min on {torch.get_num_threads()} "
        f"threads ({timing})\n\n{budget}; world models: {', '.join(f'`{c}`' for c in checkpoints)}; CEM "
        f"{args.candidates} candidates × {args.iterations} iterations, {args.elites} "
        f"elites\n\n{table(rows)}\n"
    )
    if aggregation:
        text += (
            "\n## Data aggregation\n\nRound r records with the MPC agent of round r - 1's world model "
            "(all sensors, plus exploration bursts), and trains round r's world model on the union; "
            "the last round's world models are the ones played above. Recording success: the object "
            f"within {100 * SUCCESS_DISTANCE:.0f} cm of the goal at some recorded frame.\n\n"
            f"{aggregation_table(aggregation)}\n"
        )
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "results.md", text)
    write_json(
        args.out / "results.json",
        {
            "rows": rows,
            "aggregation": aggregation,
            "episodes": raw,
            "phases_s": phases,
            "args": {k: str(v) for k, v in vars(args).items()},
        },
    )
    print(text)
    first = args.outage[0]
    spread = ", ".join(
        f"{label} {rows[f'mpc {label}']['success_min']:.0f}-{rows[f'mpc {label}']['success_max']:.0f}%"
        for label, _, _ in conditions
    )
    decision = statistics.median(rows[f"mpc {label}"]["decision_ms"] for label, _, _ in conditions)
    print(
        "spread over world-model seeds "
        f"{args.world_model_seeds if not args.checkpoint else len(checkpoints)}: "
        f"{spread}; MPC decision {decision:.1f} ms/step (median)"
    )
    print(
        f"summary: success all {rows['mpc all']['success']:.0f}%, "
        f"no-camera {rows[f'mpc no-camera ({first})']['success']:.0f}%, "
        f"no-force {rows[f'mpc no-force ({first})']['success']:.0f}%, scripted "
        f"{rows['scripted']['success']:.0f}%, "
        f"random {rows['random']['success']:.0f}%"
    )


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    np.set_printoptions(precision=3)
    main()
