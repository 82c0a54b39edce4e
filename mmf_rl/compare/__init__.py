"""The comparison protocol on any data: entries x presence subsets x seeds, trained and scored with
resume, paired bootstrap intervals over test episodes, coverage, the latent's KL, the markdown report
and its summary line. ``mmf-rl compare`` runs it from the command line; ``benchmarks/accuracy.py``
runs it on the push data with the paper's entries."""

from mmf_rl.compare.bootstrap import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    LEVEL,
    Cell,
    Table,
    bootstrap_cell,
    bootstrap_unit,
    bootstrap_weights,
    build_table,
    episode_totals,
)
from mmf_rl.compare.collect import Collected, collect_runs, timing
from mmf_rl.compare.entries import CATALOGUE, DEFAULT_ENTRIES, Budget, Entry, Study, run_plan, subsets
from mmf_rl.compare.runs import check_entries, check_reused, open_data, run_one, run_pending, window_errors
from mmf_rl.compare.summary import paired_comparisons, summarize, summarize_against_best_baseline

__all__ = [
    "BOOTSTRAP_RESAMPLES",
    "BOOTSTRAP_SEED",
    "CATALOGUE",
    "DEFAULT_ENTRIES",
    "LEVEL",
    "Budget",
    "Cell",
    "Collected",
    "Entry",
    "Study",
    "Table",
    "bootstrap_cell",
    "bootstrap_unit",
    "bootstrap_weights",
    "build_table",
    "check_entries",
    "check_reused",
    "collect_runs",
    "episode_totals",
    "open_data",
    "paired_comparisons",
    "run_one",
    "run_pending",
    "run_plan",
    "subsets",
    "summarize",
    "summarize_against_best_baseline",
    "timing",
    "window_errors",
]
