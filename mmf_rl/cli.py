"""`mmf-rl <command> [args]`: one entry point, one module per command.

Commands are imported lazily so that `mmf-rl --help` stays fast and a command's heavy
dependencies (MuJoCo, lerobot) load only when it runs.
"""

from __future__ import annotations

import importlib
import sys

# command -> (module exposing `main(argv: list[str]) -> int | None`, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "record": ("mmf_rl.record", "record a multimodal push dataset (LeRobot v3.0)"),
    "train": ("mmf_rl.trainers.run", "train a forecaster on a LeRobot dataset (Hydra overrides)"),
    "eval": ("mmf_rl.eval.run", "evaluate a checkpoint on every presence subset: table and plots"),
    "inspect": (
        "mmf_rl.datasets.inspect",
        "report a LeRobot dataset's features, cameras, NaN spans and outages; suggest a data config",
    ),
    "bench": ("mmf_rl.bench", "run a benchmark of benchmarks/ (accuracy, data, model, mpc)"),
    "demo": ("mmf_rl.demo", "record a push dataset, train the default model on CPU, evaluate (make demo)"),
}


def _usage() -> str:
    lines = ["usage: mmf-rl <command> [args]", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in sorted(COMMANDS.items())]
    if not COMMANDS:
        lines.append("  (none yet)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"mmf-rl: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module = importlib.import_module(COMMANDS[name][0])
    try:
        return int(module.main(rest) or 0)
    except SystemExit as exit_:  # argparse's --help (0) and usage errors (2)
        return exit_.code if isinstance(exit_.code, int) else 1


if __name__ == "__main__":
    sys.exit(main())
