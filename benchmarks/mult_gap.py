"""Where MulT's all-sensor advantage on push comes from: hybrids of MulT and the paper model.

    .venv/bin/python benchmarks/mult_gap.py --jobs 2   # every row, 3 seeds, two runs at once
    .venv/bin/python benchmarks/mult_gap.py --entries paper MulT --seeds 0
    .venv/bin/python benchmarks/mult_gap.py --tiny     # smoke run of the code paths (numbers mean nothing)

With every sensor, MulT forecasts push better than the paper model. The two differ in their tokens
(MulT: one per step; the paper: one per modality's window), in how modalities meet (MulT: one
cross-modal Transformer per ordered pair; the paper: self-attention over all tokens) and in the
readout (MulT: the pairs' last-step readouts concatenated into the head; the paper: a joint MLP with
the latent, then two fixed-query attentions). Each hybrid swaps one of these, so the table attributes
the gap. Every row is trained and scored by ``mmf_rl.compare`` (as ``benchmarks/
accuracy.py``) with one budget: 1000 steps of batch 32 at 32x32 on the push recording, seeds 0 1 2,
every presence subset of the same test episodes.

The hybrids are the models of ``benchmarks/mult_gap_models.py``, registered under ``gap_*`` names each
time this script runs or is imported (so the worker processes of ``--jobs``, which run it again, build
them too). Their checkpoints load only where they are registered: in ``mmf-rl eval`` or
``load_trained_model`` they are unknown models.

The recording is made if ``--data`` does not exist, by ``mmf_rl.compare.script`` as for
``benchmarks/accuracy.py`` (same default path, episodes and seed, so the two share it). Completed runs
in ``--out`` are reused: an interrupted run resumes. Writes ``<out>/results.md`` (MSE per row and
presence subset, mean over seeds; all-sensor 95% paired bootstrap intervals against MulT; each row's
all-sensor MSE on training windows beside test, which tells a row that fits worse from one that
generalises worse) and
``<out>/results.json``, and ends with one line: ``summary: MulT all A; MulT on the paper's tokens B
(fixed-query readout C); paper D``
(all-sensor MSE means; ``-`` for a row not run).
"""

from __future__ import annotations

import argparse
import os
import runpy
import statistics
from pathlib import Path

from mmf_rl.compare import entries as catalogue
from mmf_rl.compare import report, script
from mmf_rl.compare.bootstrap import Table, build_table, difference_interval
from mmf_rl.compare.entries import Entry, Study, subsets

# The hybrids register as their module runs, which it does here, by path, each time this script runs:
# `mmf-rl bench` puts neither benchmarks/ nor the checkout on sys.path, and a cached import would not
# register them again in a process whose registry a test has reset.
runpy.run_path(str(Path(__file__).with_name("mult_gap_models.py")), run_name="mult_gap_models")

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ("force", "image", "proprio")
PAPER = ("model=forecaster",)
MULT = ("model=mult",)
MULT_TOKENS = "MulT on the paper's tokens"
MULT_TOKENS_FQ = "MulT on the paper's tokens, fixed-query readout"
ENTRIES = [
    catalogue.PAPER,
    catalogue.MULT,
    Entry("MulT, fixed-query readout", "zero-fill", (*MULT, "model.name=gap_mult_fq")),
    Entry(MULT_TOKENS, "zero-fill", (*MULT, "model.name=gap_mult_tok1")),
    Entry(MULT_TOKENS_FQ, "zero-fill", (*MULT, "model.name=gap_mult_tok1_fq")),
    Entry(
        "MulT on the paper's tokens, one layer shared by the pairs",
        "zero-fill",
        (*MULT, "model.name=gap_mult_shared"),
    ),
    Entry("MulT, frame-stacked image token", "zero-fill", (*MULT, "model.name=gap_mult_stackimg")),
    Entry("MulT, self pairs too", "zero-fill", (*MULT, "model.name=gap_mult_self")),
    Entry("MulT, the paper's per-step vector tokens", "zero-fill", (*MULT, "model.name=gap_mult_steptok")),
    Entry("paper, no decoder joint MLP", "variant", (*PAPER, "model.name=gap_fc_nojoint")),
    Entry("paper, one joint MLP per modality", "variant", (*PAPER, "model.name=gap_fc_pm")),
    Entry("paper, residual joint MLP", "variant", (*PAPER, "model.name=gap_fc_res")),
    Entry("paper, pair tokens", "variant", (*PAPER, "model.name=gap_fc_pair", "model.decoder_input=tokens")),
    Entry("paper, 4 queries per modality", "variant", (*PAPER, "model.name=gap_fc_q4")),
    Entry("paper, MLP after each aggregation", "variant", (*PAPER, "model.name=gap_fc_post")),
    Entry(
        "paper, deterministic",
        "ablation",
        (*PAPER, "loss=no_mis", "loss.kl_weight=0", "model.eval_latent=posterior"),
    ),
    catalogue.NO_MIS,
]
SUBSET_COLUMNS = {
    "all": "all",
    "without_force": "w/o force",
    "without_image": "w/o image",
    "without_proprio": "w/o proprio",
    "only_force": "force only",
    "only_image": "image only",
    "only_proprio": "proprio only",
}


# Every row, 3 seeds, 1000 steps of batch 32 at 32x32 on accuracy.py's recording of 200 episodes.
STANDARD = script.Mode(image_size=32, batch_size=32, steps=1000, seeds=(0, 1, 2), entries=None, episodes=200)
# Tiny: the code paths (a paper hybrid with pair tokens, a MulT hybrid with both swaps) in seconds;
# the numbers mean nothing.
TINY = script.Mode(
    image_size=32,
    batch_size=8,
    steps=4,
    seeds=(0,),
    entries=("paper", MULT_TOKENS_FQ, "paper, pair tokens"),
    episodes=16,
)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiny", action="store_true", help="smoke run: 1 seed, 4 steps of batch 8, 3 rows")
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="recorded push dataset (default data/push_bench_<episodes>ep, as benchmarks/accuracy.py; "
        "recorded if absent)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="runs and results (default runs/bench_mult_gap_<mode>)"
    )
    script.add_override_flags(parser, "seeds")
    parser.add_argument("--entries", nargs="+", default=None, help="the rows to run (labels; default all)")
    script.add_run_flags(parser)
    args = parser.parse_args(argv)
    script.check_run_flags(parser, args, ENTRIES, paper_required=False)
    args.mode = "tiny" if args.tiny else "standard"
    args.budget = (TINY if args.tiny else STANDARD).overridden(args)
    args.data = (args.data or script.push_recording_path(REPO, args.budget.episodes)).resolve()
    args.out = (args.out or REPO / "runs" / f"bench_mult_gap_{args.mode}").resolve()
    return args


def mse_table(table: Table, labels: list[str], seeds: int) -> str:
    """Rows x the presence subsets and their mean: test MSE, mean over seeds."""
    names = [s for s in SUBSET_COLUMNS if s in table.subsets]
    lines = [
        "| model | seeds | " + " | ".join(SUBSET_COLUMNS[s] for s in names) + " | mean of 7 |",
        "|---" * (len(names) + 3) + "|",
    ]
    for label in labels:
        cells = table.cells[label]
        means = [cells[s].mean for s in names if s in cells]
        mean = f"{statistics.fmean(means):.3f}" if len(means) == len(SUBSET_COLUMNS) else "-"
        row = " | ".join(f"{cells[s].mean:.3f}" if s in cells else "-" for s in names)
        lines.append(f"| {label} | {seeds} | {row} | {mean} |")
    return "\n".join(lines)


def against_mult(table: Table, labels: list[str]) -> str:
    """All-sensor MSE with its 95% interval, and the paired difference to MulT (negative: better)."""
    lines = ["| model | all sensors [95% interval] | minus MulT [95% interval] |", "|---|---|---|"]
    mult = table.cells.get(catalogue.MULT.label, {}).get("all")
    for label in labels:
        cell = table.cells[label].get("all")
        if cell is None:
            continue
        difference = "-"
        if mult is not None and label != catalogue.MULT.label:
            low, high = difference_interval(cell, mult)
            difference = f"{cell.mean - mult.mean:+.3f} [{low:+.3f}, {high:+.3f}]"
        lines.append(f"| {label} | {cell.mean:.3f} [{cell.low:.3f}, {cell.high:.3f}] | {difference} |")
    return "\n".join(lines)


def summary_line(table: Table) -> tuple[str, dict[str, float | None]]:
    """``summary: MulT all A; MulT on the paper's tokens B (fixed-query readout C); paper D``."""
    labels = {"mult": "MulT", "tokens": MULT_TOKENS, "tokens_fq": MULT_TOKENS_FQ, "paper": "paper"}
    means = {
        key: (table.cells[label]["all"].mean if "all" in table.cells.get(label, {}) else None)
        for key, label in labels.items()
    }
    text = {key: "-" if value is None else f"{value:.3f}" for key, value in means.items()}
    line = (
        f"summary: MulT all {text['mult']}; MulT on the paper's tokens {text['tokens']} "
        f"(fixed-query readout {text['tokens_fq']}); paper {text['paper']}"
    )
    return line, means


def markdown(study: Study, table: Table, info: dict, fit: dict) -> str:
    budget, labels = study.budget, [e.label for e in study.entries]
    return (
        "# The gap to MulT with every sensor: hybrids of MulT and the paper model\n\n"
        f"Push dataset {info['data']}, split by episode, test episodes: {info['test_episodes']}; images "
        f"{budget.image_size}x{budget.image_size}. Every model: {budget.steps} steps of batch "
        f"{budget.batch_size}, seeds {', '.join(map(str, budget.seeds))}. Wall time "
        f"{info['seconds'] / 60:.1f} min ({info['reused']} of {info['runs']} runs reused).\n\n"
        "## Test MSE (normalised target), mean over seeds\n\n"
        + mse_table(table, labels, len(budget.seeds))
        + "\n\n## With every sensor, against MulT\n\n"
        "95% percentile bootstrap over the test episodes, paired (the same resamples for every row).\n\n"
        + against_mult(table, labels)
        + "\n\n"
        + report.fit_section(fit)
    )


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    study = script.push_study(args, ENTRIES, MODALITIES, paper_required=False)
    script.check_study(study, "mult_gap benchmark")
    outcome = script.run_study(study, script.PushRecording(args.data, args.budget.episodes))
    collected = outcome.collected
    table, episodes = build_table(collected.errors, collected.kinds, [n for n, _ in subsets(MODALITIES)])
    info = {
        "data": str(args.data),
        "test_episodes": len(episodes),
        "seconds": outcome.seconds,
        "runs": outcome.runs,
        "reused": outcome.reused,
    }
    line, summary = summary_line(table)
    text = markdown(study, table, info, collected.fit) + f"{line}\n"
    results = {
        "mode": args.budget.__dict__,
        "info": info,
        "cells": report.cells_json(table),
        "summary": summary,
        "fit": collected.fit,
    }
    script.report_results(args.out, text, results)
    return 0


if __name__ == "__main__":
    script.run_as_script(main)
