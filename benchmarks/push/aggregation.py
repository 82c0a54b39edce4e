"""PETS-style data aggregation for push world models: each round records episodes with the MPC agent
of the last round's world model (plus the recorder's random-move bursts), merges them with that
world model's training data and trains the next world model on the union.

Each world-model seed aggregates its own data, so the seeds stay independent replicates of the
whole procedure. Everything is built under one work directory and reused when found: a recording
or a union is published atomically, a training writes its exported model when it ends (early or
not) and an interrupted one resumes.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.push.experiment import timed_phase, train_or_resume
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.models import RUN_EXPORT_DIR
from mmf_rl.record import CAMERA_KEY, GOAL_KEY, OBJECT_POSE_KEY, RecordConfig, merge_recordings, record
from mmf_rl.rl.agent import PushMPCAgent

logger = logging.getLogger(__name__)

FIRST_RECORDING = {"seed": 1, "exploration": 0.1}  # of the data the first world models train on
SUCCESS_DISTANCE = 0.05  # FetchPush's distance_threshold, metres (3-D, object to goal)


@dataclass
class AggregationConfig:
    """What `aggregate_data` builds, and where."""

    work: Path  # holds push_explore/ (the first recording) and everything the rounds build
    seeds: list[int]  # the world models' trainer.seed, one world model each
    rounds: int
    episodes: int = 100  # recorded per round
    exploration: float = 0.1  # per-step probability of a random-move burst while the agent records
    early_stopping_patience: int = 2  # evaluations without a better val/mse before a retraining stops
    warm_start: bool = False  # retrain from the last round's weights (init_from), not from scratch
    workers: int = 2  # recording processes
    # `PushMPCAgent`'s planner sizes and reach weight
    agent: dict = field(default_factory=dict)
    # more Hydra overrides for every training (after the experiment's own)
    train_overrides: list[str] = field(default_factory=list)


def add_aggregation_arguments(parser: argparse.ArgumentParser) -> None:
    """The command-line arguments of `AggregationConfig` (``--aggregate ROUNDS`` and its options, with
    its defaults)."""
    parser.add_argument(
        "--aggregate",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="rounds of data aggregation with the MPC agent before playing (0: none)",
    )
    parser.add_argument(
        "--aggregate-episodes",
        type=int,
        default=AggregationConfig.episodes,
        help="episodes recorded per round",
    )
    parser.add_argument(
        "--aggregate-exploration",
        type=float,
        default=AggregationConfig.exploration,
        help="per-step probability of a random-move burst while the agent records (mmf-rl record "
        "--exploration)",
    )
    parser.add_argument(
        "--early-stopping-patience",
        type=int,
        default=AggregationConfig.early_stopping_patience,
        help="retrainings of the aggregation rounds stop after this many evaluations without a better "
        "val/mse",
    )
    parser.add_argument(
        "--aggregate-warm-start",
        action="store_true",
        help="retrain from the last round's weights (init_from) instead of from scratch",
    )


def check_aggregation_arguments(
    parser: argparse.ArgumentParser, args: argparse.Namespace, world_models_given: bool
) -> None:
    """Exits through ``parser.error`` on values out of range, or on aggregation with world models
    given on the command line (``--checkpoint``): it retrains on the data they were trained on."""
    if args.aggregate < 0 or args.aggregate_episodes < 1 or args.early_stopping_patience < 0:
        parser.error("--aggregate must be >= 0, --aggregate-episodes >= 1, --early-stopping-patience >= 0")
    if args.aggregate and world_models_given:
        parser.error(
            "--aggregate retrains on the data the world models were trained on: build them here "
            "(drop --checkpoint)"
        )


def train_world_model(run_dir: Path, data: Path, seed: int, overrides: Sequence[str] = ()) -> Path:
    """``mmf-rl train experiment=world_model`` on ``data`` into ``run_dir`` (resumes an interrupted
    run); returns its checkpoints directory."""
    return train_or_resume(
        [
            "experiment=world_model",
            f"name={run_dir.name}",
            f"run_dir={run_dir}",
            f"data.root={data}",
            f"trainer.seed={seed}",
            "trainer.progress_bar=false",
            *overrides,
        ]
    )


def recording_summary(root: Path) -> dict:
    """A recording's episodes, the per cent of them where the object came within
    `SUCCESS_DISTANCE` of the goal at some frame, its image size and steps per episode."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from mmf_rl.datasets.lerobot_source import load_frame_columns

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


def aggregate_data(
    config: AggregationConfig, checkpoints: list[Path], phases: dict[str, float]
) -> tuple[list[Path], list[dict]]:
    """``config.rounds`` rounds per world-model seed, starting from ``checkpoints`` (one per seed,
    trained on ``work/push_explore``); the seconds of each recording and training go to
    ``phases``. Returns the last round's world models and one row per seed and round."""
    first = recording_summary(config.work / "push_explore")
    rows, finals = [], []
    for seed, checkpoint in zip(config.seeds, checkpoints, strict=True):
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
        data = config.work / "push_explore"
        for round_ in range(1, config.rounds + 1):
            row, data, checkpoint = aggregation_round(config, seed, round_, data, checkpoint, first, phases)
            rows.append(row)
        finals.append(checkpoint)
    return finals, rows


def aggregation_round(
    config: AggregationConfig,
    seed: int,
    round_: int,
    data: Path,
    checkpoint: Path,
    first: dict,
    phases: dict[str, float],
) -> tuple[dict, Path, Path]:
    """One round of seed ``seed`` from the world model ``checkpoint`` trained on ``data``; returns
    its row, the union and the new world model's checkpoints."""
    tag = f"seed {seed} round {round_}"
    work = config.work
    recording = work / f"aggregate_seed{seed}_round{round_}"
    if not (recording / "meta" / "info.json").is_file():  # a recording is written atomically
        logger.info("[%s] recording %d MPC episodes with %s", tag, config.episodes, checkpoint)
        agent = PushMPCAgent(checkpoint, image_size=first["image_size"], **config.agent)
        with timed_phase(phases, f"aggregate {tag} record"):
            record(
                RecordConfig(
                    out=recording,
                    episodes=config.episodes,
                    workers=config.workers,
                    seed=FIRST_RECORDING["seed"] + round_,
                    image_size=first["image_size"],  # recorded as the first data, so that both merge
                    steps=first["steps"],
                    exploration=config.exploration,
                    policy=agent,
                )
            )
    union = work / f"union_seed{seed}_round{round_}"
    if not (union / "meta" / "info.json").is_file():
        merge_recordings([data, recording], union)
    run_dir = work / f"world_model_seed{seed}_round{round_}"
    if not (run_dir / RUN_EXPORT_DIR).is_dir():  # written when a training ends, early or not
        extra = [f"trainer.early_stopping_patience={config.early_stopping_patience}"]
        if config.warm_start:
            extra.append(f"init_from={Path(checkpoint).parent}")
        with timed_phase(phases, f"aggregate {tag} train"):
            train_world_model(run_dir, union, seed, [*config.train_overrides, *extra])
    recorded = recording_summary(recording)
    new_checkpoint = run_dir / "checkpoints"
    row = {
        "seed": seed,
        "round": round_,
        "recorded_by": f"MPC on round {round_ - 1}'s world model + exploration {config.exploration}",
        "episodes_recorded": recorded["episodes"],
        "episodes_trained_on": recording_summary(union)["episodes"],
        "recording_success": recorded["success"],
        "steps_trained": trained_steps(new_checkpoint),
        "world_model": str(new_checkpoint),
    }
    return row, union, new_checkpoint


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
