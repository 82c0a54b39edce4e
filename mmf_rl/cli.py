"""`mmf-rl [--verbose | --quiet] <command> [args]`: one entry point, one module per command.

Commands are imported lazily so that `mmf-rl --help` stays fast and a command's heavy
dependencies (MuJoCo, lerobot) load only when it runs. What a command exists to print (a report,
a table, a config) goes to stdout; its progress messages and warnings are log records of the
``mmf_rl`` loggers, which this entry point sends to stderr (:func:`mmf_rl.log.configure_logging`).
"""

from __future__ import annotations

import importlib
import logging
import sys
from pathlib import Path

from mmf_rl.log import configure_logging

# command -> (module exposing `main(argv: list[str]) -> int | None`, or "module:function" for
# another such function, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "record": (
        "mmf_rl.cli:record",
        "record a multimodal push dataset (LeRobot v3.0), scripted or by an MPC agent; merge recordings",
    ),
    "train": ("mmf_rl.trainers.train_command", "train a forecaster on a LeRobot dataset (Hydra overrides)"),
    "eval": ("mmf_rl.eval.eval_command", "evaluate a checkpoint on every presence subset: table and plots"),
    "calibrate": (
        "mmf_rl.eval.calibrate_command",
        "fit a trained model's forecast scale per presence pattern on its val split; store it with the model",
    ),
    "inspect": (
        "mmf_rl.datasets.inspect",
        "report a LeRobot dataset's features, cameras, NaN spans and outages; suggest a data config",
    ),
    "import": (
        "mmf_rl.datasets.ethucy",
        "convert a public dataset to LeRobot v3.0 with its data config (ethucy: ETH/UCY pedestrians)",
    ),
    "compare": (
        "mmf_rl.compare.command",
        "train and compare the paper model with baselines on any data config, every presence subset",
    ),
    "bench": ("mmf_rl.bench", "run a benchmark of benchmarks/ (accuracy, data, model, mpc)"),
    "demo": ("mmf_rl.demo", "record a push dataset, train the default model on CPU, evaluate (make demo)"),
}


def record(argv: list[str]) -> int:
    """`mmf-rl record`: `mmf_rl.record`'s command plus ``--policy CHECKPOINT`` (record with MPC on
    that world model). The recorder sits below the models and cannot load one: the agent's
    factory (`mmf_rl.rl.PushMPCAgent`) is built here, checked once, and passed down."""
    from mmf_rl import record as recorder

    parser = recorder.build_parser()
    agent = parser.add_argument_group(
        "recording with an MPC agent",
        "  instead of the scripted pusher: SequenceCEMPlanner + PushObjective on a world model, one\n"
        "  agent per worker; --exploration adds the same random-move bursts",
    )
    agent.add_argument(
        "--policy", type=Path, metavar="CHECKPOINT", help="world model: a run dir or its checkpoints/"
    )
    agent.add_argument("--candidates", type=int, default=128, help="CEM candidates per iteration")
    agent.add_argument("--iterations", type=int, default=4, help="CEM iterations per step")
    agent.add_argument("--elites", type=int, default=16, help="CEM elites")
    agent.add_argument("--reach-weight", type=float, default=0.5, help="PushObjective's reach_weight")
    args = parser.parse_args(argv)
    policy = None
    if args.policy is not None:
        from mmf_rl.checkpoint import CheckpointError
        from mmf_rl.rl import PushMPCAgent

        try:
            policy = PushMPCAgent(
                args.policy,
                image_size=args.image_size,
                num_candidates=args.candidates,
                num_iterations=args.iterations,
                num_elites=args.elites,
                reach_weight=args.reach_weight,
            )
        except (CheckpointError, OSError, ValueError, KeyError) as error:
            message = error.args[0] if isinstance(error, KeyError) and error.args else error
            print(f"{recorder.PROG}: error: --policy {args.policy}: {message}", file=sys.stderr)
            return 2
    return recorder.run(args, policy)


# top-level option -> level of the mmf_rl log records shown
LOG_LEVELS = {
    "-v": logging.DEBUG,
    "--verbose": logging.DEBUG,
    "-q": logging.WARNING,
    "--quiet": logging.WARNING,
}


def _usage() -> str:
    lines = [
        "usage: mmf-rl [-v | --verbose | -q | --quiet] <command> [args]",
        "",
        "options:",
        "  -v, --verbose  also show debug messages",
        "  -q, --quiet    show warnings and errors only, not progress messages",
        "",
        "commands:",
    ]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in sorted(COMMANDS.items())]
    if not COMMANDS:
        lines.append("  (none yet)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    level = logging.INFO
    while argv and argv[0] in LOG_LEVELS:  # before the command: what follows it is the command's
        level = LOG_LEVELS[argv.pop(0)]
    configure_logging(level)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"mmf-rl: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module, _, function = COMMANDS[name][0].partition(":")
    command = getattr(importlib.import_module(module), function or "main")
    try:
        return int(command(rest) or 0)
    except SystemExit as exit_:  # argparse's --help (0) and usage errors (2), a script's error message
        if exit_.code is None or isinstance(exit_.code, int):
            return exit_.code or 0
        print(exit_.code, file=sys.stderr)  # as the interpreter shows `raise SystemExit("message")`
        return 1


if __name__ == "__main__":
    sys.exit(main())
