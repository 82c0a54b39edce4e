"""`mmf-rl demo`: record a push dataset (if absent), train the default forecaster on CPU, evaluate.

    mmf-rl demo [--data data/push] [--run-dir runs/demo] [--episodes 150] [-- hydra overrides...]

Re-running it reuses the recording, resumes (or skips) training from the run's checkpoints and
evaluates again, so an interrupted demo never starts over.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

from mmf_rl.checkpoint import CheckpointError, list_checkpoints
from mmf_rl.configuration import ConfigError
from mmf_rl.eval.evaluation import evaluate
from mmf_rl.record import RecordConfig, record
from mmf_rl.trainers.training import train

logger = logging.getLogger(__name__)


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mmf-rl demo",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  mmf-rl demo                                   # what `make demo` runs\n"
        "  mmf-rl demo --episodes 60 -- trainer.total_steps=300 model=lf_lstm   # smaller, another model",
    )
    parser.add_argument(
        "--data", type=Path, default=Path("data/push"), help="push dataset (recorded if absent)"
    )
    parser.add_argument("--run-dir", type=Path, default=Path("runs/demo"))
    parser.add_argument(
        "--episodes", type=int, default=150, help="episodes to record when the dataset is absent"
    )
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("overrides", nargs="*", help="extra `mmf-rl train` overrides (after --)")
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    started = time.perf_counter()
    try:
        if not (args.data / "meta" / "info.json").is_file():
            logger.info("recording %d push episodes into %s", args.episodes, args.data)
            record(
                RecordConfig(
                    out=args.data, episodes=args.episodes, workers=args.workers, image_size=64, steps=50
                )
            )
        else:
            logger.info("using the recording in %s", args.data)
        overrides = ["experiment=demo", f"data.root={args.data}", f"run_dir={args.run_dir}", *args.overrides]
        if list_checkpoints(args.run_dir / "checkpoints"):
            logger.info("%s has checkpoints: resuming (nothing to do if training had finished)", args.run_dir)
            overrides.append("resume=true")
        recorded = time.perf_counter()
        train(overrides=overrides)
        trained = time.perf_counter()
        summary = evaluate(overrides=[f"checkpoint={args.run_dir}"])
    except (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError) as err:
        if os.environ.get("MMF_RL_DEBUG"):
            raise
        print(f"mmf-rl demo: error: {err}", file=sys.stderr)
        return 1
    finished = time.perf_counter()
    print()
    print(summary["table"])
    for path in summary["plots"]:
        print(f"plot: {path}")
    model, baseline = summary["subsets"]["all"], summary["constant_velocity"]
    if baseline:
        print(
            f"all modalities: MSE {model['mse']:.4f} vs constant velocity {baseline['mse']:.4f} "
            f"({model['mse'] / baseline['mse'] - 1:+.0%}); ADE {model['ade']:.4f} vs {baseline['ade']:.4f}"
        )
    print(
        f"demo: {finished - started:.0f} s (record {recorded - started:.0f} s, train "
        f"{trained - recorded:.0f} s, "
        f"evaluate {finished - trained:.0f} s)"
    )
    return 0
