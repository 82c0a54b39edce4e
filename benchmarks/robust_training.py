"""Architecture vs training: is a forecaster's robustness to a missing sensor its architecture's or its
training's? And which trained forecaster is best in every presence subset?

    .venv/bin/python benchmarks/robust_training.py --jobs 2               # push, 16 cells x 3 seeds
    .venv/bin/python benchmarks/robust_training.py --humanoid --jobs 2    # the humanoid slice, 2 seeds
    .venv/bin/python benchmarks/robust_training.py --tiny                 # smoke run (numbers mean nothing)

The grid: each architecture (``ARCHITECTURES``: the paper model, the paper model with MulT's pair-stream
decoder over per-step vector tokens and a linear latent, MulT, LF-LSTM) x each training
(``TRAININGS``): complete windows only (the paper model without ``L_mis``, the baselines as they are),
modality dropout drawn every batch (``loss.modality_dropout=subsets``: half the samples keep a
uniformly drawn non-empty subset of their sensors), ``L_mis`` (the paper's consistency term: the
model's own supervised term plus ``mis``), and both. Every cell is trained and scored by
``mmf_rl.compare`` with one budget (push: 1000 steps of batch 32 at 32x32 on ``benchmarks/accuracy.py``'s
recording, seeds 0 1 2; the humanoid slice: ``benchmarks/real_humanoid.py``'s data, 1000 steps of batch
64, seeds 0 1) and scored on every presence subset of the test split.

The recommendation is chosen on the validation split only: every cell's MSE per subset on val (mean
over seeds); the pick is the cell whose worst ratio to the best val MSE of a subset is lowest (best
everywhere if that ratio is 1). The test split then says whether it is best or tied (95% paired
bootstrap; overlapping intervals) in every subset against every cell, and the paired intervals where a
cell beats it. Completed runs in ``--out`` are reused. Writes
``<out>/results.md`` and ``<out>/results.json`` and ends with one line: ``summary: recommended (val)
NAME; test best or tied in X/7 subsets against every cell (paired: beaten in K); all sensors A (best
cell B); mean degradation D%``.
"""

from __future__ import annotations

import argparse
import json
import os
import runpy
import statistics
from functools import partial
from pathlib import Path

import torch

from mmf_rl.compare import entries as catalogue
from mmf_rl.compare import report, script
from mmf_rl.compare.bootstrap import Table, best_or_tied, bootstrap_unit, build_table, difference_interval
from mmf_rl.compare.entries import Entry, Study, run_plan, select_entries, subsets

REPO = Path(__file__).resolve().parents[1]
HUMANOID = runpy.run_path(str(Path(__file__).with_name("real_humanoid.py")), run_name="real_humanoid")
TRAININGS = ("complete windows", "modality dropout", "L_mis", "modality dropout + L_mis")
DROPOUT = catalogue.DROPOUT


def pair_streams(vectors: tuple[str, ...]) -> tuple[str, ...]:
    """The paper model with MulT's pair streams as the decoder's input, over one token per step of each
    vector sensor, and a linear latent (the push benchmark's closest entry to MulT)."""
    steps = tuple(f"data.modalities.{m}.encoder=steps" for m in vectors)
    return ("model=forecaster", "model.decoder_input=pair_streams", "model.decoder_latent=linear", *steps)


def grid(vectors: tuple[str, ...], data: tuple[str, ...] = ()) -> list[Entry]:
    """Every architecture x training; ``vectors``: the data's vector sensors, ``data``: overrides choosing
    the data, first in every cell."""
    architectures = {
        "paper": ("model=forecaster",),
        "paper, pair-stream decoder": pair_streams(vectors),
        "MulT": ("model=mult",),
        "LF-LSTM": ("model=lf_lstm",),
    }
    cells = []
    for architecture, overrides in architectures.items():
        paper_like = overrides[0] == "model=forecaster"
        if paper_like:
            trainings = {
                "complete windows": ("loss=no_mis",),
                "modality dropout": ("loss=no_mis", *DROPOUT),
                "L_mis": (),
                "modality dropout + L_mis": DROPOUT,
            }
        else:
            trainings = {"complete windows": (), **catalogue.missing_sensor_trainings("nll")}
        for training, extra in trainings.items():
            label = (
                "paper" if (architecture, training) == ("paper", "L_mis") else f"{architecture}; {training}"
            )
            kind = "paper" if label == "paper" else "variant" if paper_like else "zero-fill"
            if not paper_like and training != "complete windows":
                kind = catalogue.TRAINED_FOR_MISSING_KIND
            cells.append(Entry(label, kind, (*data, *overrides, *extra)))
    return cells


PUSH_MODALITIES = ("force", "image", "proprio")
PUSH = grid(("force", "proprio"))
HUMANOID_GRID = grid(("state", "action"), (*HUMANOID["DATA"], HUMANOID["SENSOR_FEATURES"]))
STANDARD = script.Mode(image_size=32, batch_size=32, steps=1000, seeds=(0, 1, 2), entries=None, episodes=200)
HUMANOID_MODE = script.Mode(32, 64, 1000, (0, 1), None, 0)
TINY = script.Mode(32, 8, 4, (0,), ("paper", "MulT; modality dropout + L_mis"), 16)


def architecture_and_training(label: str) -> tuple[str, str]:
    return ("paper", "L_mis") if label == "paper" else tuple(label.split("; "))


@torch.no_grad()
def val_mse(study: Study, entry: Entry) -> dict[str, float]:
    """The entry's val MSE per presence subset, mean over seeds (kept in each run's ``eval/val_mse.json``)."""
    from mmf_rl.compare.runs import subset_errors, trained_model_and_data
    from mmf_rl.eval.report import write_json

    per_seed = []
    for *_, run_dir, _, _ in run_plan(entry, study):
        path = run_dir / "eval" / "val_mse.json"
        if not path.is_file():
            model, data = trained_model_and_data(run_dir, study.device)
            errors = {
                name: subset_errors(model, data, subset, study.device, 256, split="val")["squared_error"]
                for name, subset in subsets(study.modalities)
            }
            write_json(path, {name: statistics.fmean(e) for name, e in errors.items() if e})
        per_seed.append(json.loads(path.read_text()))
    return {name: statistics.fmean(seed[name] for seed in per_seed) for name in per_seed[0]}


def recommended(val: dict[str, dict[str, float]]) -> tuple[str, float]:
    """The cell whose worst ratio to a subset's best val MSE is lowest, and that ratio."""
    names = list(next(iter(val.values())))
    best = {name: min(cell[name] for cell in val.values()) for name in names}
    worst = {label: max(cell[name] / best[name] for name in names) for label, cell in val.items()}
    pick = min(worst, key=worst.get)
    return pick, worst[pick]


def wins_against_all(table: Table, label: str) -> int:
    """Subsets where ``label`` is best or tied among every cell of the table."""
    return sum(
        best_or_tied({other: table.cells[other][s] for other in table.kinds}, label) for s in table.subsets
    )


def paired_table(table: Table, pick: str, title) -> str:
    """The pick against every other cell, per subset: its MSE minus the cell's with the 95% paired
    interval; ``worse``/``better`` where the interval excludes 0. Overlapping marginal intervals (the
    "best or tied" count) hide a difference the paired interval finds."""
    others = [label for label in table.kinds if label != pick]
    lines = ["| cell | " + " | ".join(title(s) for s in table.subsets) + " |"]
    lines.append("|---" * (len(table.subsets) + 1) + "|")
    for other in others:
        cells = []
        for s in table.subsets:
            low, high = difference_interval(table.cells[pick][s], table.cells[other][s])
            verdict = " worse" if low > 0 else " better" if high < 0 else ""
            cells.append(f"{table.cells[pick][s].mean - table.cells[other][s].mean:+.3f}{verdict}")
        lines.append(f"| {other} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def subsets_lost(table: Table, pick: str) -> list[str]:
    """The subsets where some cell beats ``pick`` beyond the paired interval."""
    return [
        s
        for s in table.subsets
        if any(difference_interval(table.cells[pick][s], table.cells[o][s])[0] > 0 for o in table.kinds)
    ]


def grid_table(table: Table) -> str:
    """Architecture rows x training columns: all-sensor test MSE [95% interval] / mean degradation."""
    lines = ["| architecture | " + " | ".join(TRAININGS) + " |", "|---" * (len(TRAININGS) + 1) + "|"]
    rows: dict[str, dict[str, str]] = {}
    for label in table.kinds:
        architecture, training = architecture_and_training(label)
        cell = table.cells[label]["all"]
        rows.setdefault(architecture, {})[training] = (
            f"{cell.mean:.3f} [{cell.low:.3f}, {cell.high:.3f}] / {100 * table.mean_degradation(label):+.0f}%"
        )
    for architecture, cells in rows.items():
        lines.append(f"| {architecture} | " + " | ".join(cells.get(t, "-") for t in TRAININGS) + " |")
    return "\n".join(lines)


def val_table(val: dict[str, dict[str, float]], title) -> str:
    names = list(next(iter(val.values())))
    lines = ["| cell | " + " | ".join(title(n) for n in names) + " |", "|---" * (len(names) + 1) + "|"]
    for label, cell in val.items():
        lines.append(f"| {label} | " + " | ".join(f"{cell[n]:.3f}" for n in names) + " |")
    return "\n".join(lines)


def summary_line(table: Table, pick: str) -> tuple[str, dict]:
    best_all = min(table.kinds, key=lambda label: table.cells[label]["all"].mean)
    summary = {
        "recommended": pick,
        "test_best_or_tied": wins_against_all(table, pick),
        "subsets_lost_paired": subsets_lost(table, pick),
        "subsets": len(table.subsets),
        "all_sensors": table.cells[pick]["all"].mean,
        "best_all_sensors": best_all,
        "best_all_sensors_mse": table.cells[best_all]["all"].mean,
        "mean_degradation": table.mean_degradation(pick),
    }
    line = (
        f"summary: recommended (val) {pick}; test best or tied in {summary['test_best_or_tied']}/"
        f"{summary['subsets']} subsets against every cell (paired: beaten in "
        f"{len(summary['subsets_lost_paired'])}); all sensors {summary['all_sensors']:.3f} (best "
        f"cell {best_all} {summary['best_all_sensors_mse']:.3f}); mean degradation "
        f"{100 * summary['mean_degradation']:.0f}%"
    )
    return line, summary


def markdown(study: Study, table: Table, val: dict, pick: tuple[str, float], collected, info: dict) -> str:
    title = partial(report.subset_title, modalities=study.modalities)
    budget = study.budget
    return (
        "# Architecture vs training for missing sensors\n\n"
        f"Data {info['data']}; test episodes {info['test_episodes']}. Every cell: {budget.steps} steps of "
        f"batch {budget.batch_size}, seeds {', '.join(map(str, budget.seeds))}. Protocol of each row: "
        "`paper`/`variant` (the paper model, the pair-stream decoder), `zero-fill` (a baseline trained on "
        "complete windows), `trained for missing` (a baseline trained with modality dropout, L_mis or "
        "both).\n\n## Architecture x training (test)\n\nAll-sensor MSE (normalised target, mean over "
        "seeds) [95% paired bootstrap interval] / mean degradation over the six degraded subsets.\n\n"
        + grid_table(table)
        + "\n\n## The recommendation, chosen on val\n\nVal MSE per subset, mean over seeds. Pick: "
        f"**{pick[0]}**, within {100 * (pick[1] - 1):.1f}% of the best cell in every subset.\n\n"
        + val_table(val, title)
        + "\n\n## The pick against every cell (test, paired)\n\nIts MSE minus the cell's, mean over "
        "seeds; `worse`/`better`: the 95% paired bootstrap interval excludes 0.\n\n"
        + paired_table(table, pick[0], title)
        + "\n\n## Test MSE per subset\n\n"
        + report.mse_table(table, list(table.kinds), list(table.kinds), title)
        + "\n\n## Relative degradation\n\n"
        + report.degradation_table(table, list(table.kinds), title)
        + "\n\n"
        + report.coverage_section(collected.coverage, table, title)
        + report.interval_quality_section(collected.intervals, table, title)
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    which = parser.add_mutually_exclusive_group()
    which.add_argument("--tiny", action="store_true", help="smoke run: 4 steps of batch 8, 2 cells")
    which.add_argument("--humanoid", action="store_true", help="benchmarks/real_humanoid.py's recording")
    parser.add_argument("--data", type=Path, default=None, help="push recording or humanoid root")
    parser.add_argument("--out", type=Path, default=None, help="runs and results")
    script.add_override_flags(parser, "seeds")
    parser.add_argument("--entries", nargs="+", default=None, help="cells to run (labels; default all)")
    script.add_run_flags(parser)
    args = parser.parse_args(argv)
    args.grid = HUMANOID_GRID if args.humanoid else PUSH
    script.check_run_flags(parser, args, args.grid)
    args.mode = "humanoid" if args.humanoid else "tiny" if args.tiny else "standard"
    args.budget = {"humanoid": HUMANOID_MODE, "tiny": TINY, "standard": STANDARD}[args.mode].overridden(args)
    default_data = HUMANOID["DEFAULT_ROOT"] if args.humanoid else script.push_recording_path(REPO, 200)
    args.data = (args.data or default_data).resolve()
    args.out = (args.out or REPO / "runs" / f"bench_robust_training_{args.mode}").resolve()
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    modalities = HUMANOID["MODALITIES"] if args.humanoid else PUSH_MODALITIES
    study = script.push_study(args, args.grid, modalities)
    script.check_study(study, "robust training benchmark")
    recording = None if args.humanoid else script.PushRecording(args.data, args.budget.episodes)
    outcome = script.run_study(study, recording)
    collected = outcome.collected
    names = [name for name, _ in subsets(modalities)]
    unit = bootstrap_unit(collected.errors, HUMANOID["BLOCK"], HUMANOID["MIN_EPISODES"])
    table, episodes = build_table(collected.errors, collected.kinds, names, unit=unit)
    val = {entry.label: val_mse(study, entry) for entry in select_entries(args.grid, args.budget.entries)}
    pick = recommended(val)
    info = {"data": str(args.data), "test_episodes": len(episodes), "seconds": outcome.seconds}
    line, summary = summary_line(table, pick[0])
    text = markdown(study, table, val, pick, collected, info) + f"{line}\n"
    results = {"mode": args.budget.__dict__, "info": info, "val": val, "cells": report.cells_json(table)}
    script.report_results(args.out, text, {**results, "summary": summary})
    return 0


if __name__ == "__main__":
    script.run_as_script(main)
