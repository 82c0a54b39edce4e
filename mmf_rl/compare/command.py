"""`mmf-rl compare [options] [OVERRIDE ...]`: the paper model against baselines on any data config.

Every entry is trained with the same steps, batch size and seeds on the same data (the data config's
split by episode), scored on every presence subset of the test split, and each cell gets a paired
bootstrap interval over test episodes (over blocks of consecutive windows when the test split has too
few episodes). Completed runs in ``--out`` are reused, so an interrupted comparison resumes; one
trained with another budget or config (a default changed since included) is refused. Writes
``<out>/results.md`` and ``<out>/results.json``, prints the report and ends with one line:
``summary: all sensors paper MSE A vs best baseline B (NAME): paper/best = R (target <= X); mean
degradation without a sensor paper P%, best baseline Q%``.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from mmf_rl.compare.bootstrap import Table, bootstrap_unit, build_table
from mmf_rl.compare.collect import Collected, timing
from mmf_rl.compare.entries import CATALOGUE, DEFAULT_ENTRIES, Budget, Study, select_entries, subsets
from mmf_rl.compare.report import (
    intervals_text,
    results_sections,
    run_time_section,
    subset_title,
    tables_json,
)
from mmf_rl.compare.runs import check_entries, check_reused
from mmf_rl.compare.script import add_run_flags, check_run_flags, report_results, run_study
from mmf_rl.compare.summary import paired_comparisons, summarize_against_best_baseline
from mmf_rl.configuration import add_config_dir_flag

logger = logging.getLogger(__name__)
PROG = "mmf-rl compare"
EXAMPLES = [
    "mmf-rl compare data=/path/to/mine.yaml --out runs/compare_mine   # paper vs zero-fill baselines",
    "mmf-rl compare data=so101 --entries paper LF-LSTM 'LF-LSTM (retrained)' --seeds 0 --steps 200",
    "mmf-rl compare data.root=/data/push --jobs 2     # two runs at once, one thread each",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="entries:\n"
        + "\n".join(f"  {e.label!r:<42} {e.kind}" for e in CATALOGUE)
        + "\n\nexamples:\n"
        + "\n".join(f"  {example}" for example in EXAMPLES),
    )
    parser.add_argument(
        "overrides",
        nargs="*",
        metavar="OVERRIDE",
        help="Hydra overrides of every run's train config: the data (data=NAME or data=/path/to/mine.yaml)",
    )
    parser.add_argument(
        "--entries", nargs="+", default=list(DEFAULT_ENTRIES), help="labels, 'paper' among them"
    )
    parser.add_argument(
        "--seeds", type=int, nargs="+", default=[0, 1, 2], help="training seeds of every entry"
    )
    parser.add_argument("--steps", type=int, default=1000, help="training steps of every run")
    parser.add_argument("--batch-size", type=int, default=32, help="training batch size of every run")
    parser.add_argument(
        "--image-size", type=int, default=None, help="square image size (default: the data config's)"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/compare"), help="runs and results")
    add_run_flags(parser)
    parser.add_argument("--target-ratio", type=float, default=1.05, help="paper/best baseline MSE target")
    add_config_dir_flag(parser)
    return parser


def make_study(args: argparse.Namespace) -> Study:
    """The comparison the arguments describe; its modalities are those of the composed data config."""
    from mmf_rl.configuration import compose_config

    entries = tuple(select_entries(CATALOGUE, args.entries))
    cfg = compose_config("train", [*entries[0].overrides, *args.overrides], list(args.config_dir))
    return Study(
        out=args.out.expanduser().resolve(),
        budget=Budget(args.steps, args.batch_size, tuple(args.seeds), args.image_size),
        entries=entries,
        modalities=tuple(cfg.data.modalities),
        data_overrides=tuple(args.overrides),
        config_dirs=tuple(args.config_dir),
        device=args.device,
        jobs=args.jobs,
    )


def run(study: Study, target_ratio: float) -> None:
    """Train what is missing, score, write ``results.md`` and ``results.json`` and print the report."""
    check_entries(study)
    check_reused(study)
    outcome = run_study(study)
    data, collected = outcome.data, outcome.collected
    block = data.config.history + data.config.horizon  # one window's span of frames (stride 1)
    unit = bootstrap_unit(collected.errors, block)
    names = [name for name, _ in subsets(study.modalities)]
    table, groups = build_table(collected.errors, collected.kinds, names, unit, bases=collected.bases)
    line, summary = summarize_against_best_baseline(table, target_ratio)
    comparisons = paired_comparisons(table)
    measured = timing(collected.runs)
    info = {
        "data": str(data.config.root or data.config.repo_id),
        "episodes": len({int(e) for eps in data.split_episodes.values() for e in eps}),
        "split": {name: list(map(int, eps)) for name, eps in data.split_episodes.items()},
        "unit": unit,
        "block": block,
        "groups": groups,
        **outcome.info(),
    }
    text = markdown(study, table, collected, comparisons, info, measured) + f"{line}\n"
    results = {
        "budget": study.budget.__dict__,
        "entries": {e.label: {"kind": e.kind, "overrides": list(e.overrides)} for e in study.entries},
        "data_overrides": list(study.data_overrides),
        "info": info,
        **tables_json(table, collected, comparisons, measured),
        "summary": summary,
    }
    report_results(study.out, text, results)


def markdown(
    study: Study, table: Table, collected: Collected, comparisons: dict, info: dict, measured: dict
) -> str:
    budget = study.budget
    split = info["split"]
    cv = info["constant_velocity_mse"]
    header = (
        "# Missing-modality comparison\n\n"
        f"Data {info['data']} ({' '.join(study.data_overrides) or 'the default data config'}): "
        f"{info['episodes']} episodes split by episode, train {len(split['train'])}, "
        f"val {len(split['val'])}, "
        f"test {len(split['test'])}; modalities {', '.join(study.modalities)}. Every model: {budget.steps} "
        f"steps of batch {budget.batch_size}, seeds {', '.join(map(str, budget.seeds))}. Wall time "
        f"{info['seconds'] / 60:.1f} min"
        + (f" ({info['reused']} of {info['runs']} runs reused from an earlier one)" if info["reused"] else "")
        + ".\n\n"
    )
    reference = (
        f"Reference: constant-velocity extrapolation of the target, MSE {cv:.4f}; predicting the training "
        "mean gives about 1.\n\n"
        if cv is not None
        else ""
    )
    intervals = intervals_text(info["unit"], info["groups"], split["test"], info["block"]) + "\n\n"
    return (
        header
        + results_sections(
            table, collected, comparisons, lambda s: subset_title(s, study.modalities), intervals, reference
        )
        + run_time_section(info["cache_seconds"], measured)
    )


def main(argv: list[str]) -> int:
    parser = build_parser()
    args = parser.parse_intermixed_args(argv)
    check_run_flags(parser, args)  # --entries: make_study checks it, a command error (exit code 1)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    from mmf_rl.configuration import ConfigError, report_command_error

    try:
        study = make_study(args)
        run(study, args.target_ratio)
    except (ConfigError, OSError, ValueError, KeyError) as err:
        return report_command_error(PROG, err)
    return 0
