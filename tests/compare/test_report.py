"""mmf_rl.compare.report: the markdown sections, exactly as benchmarks/accuracy.py wrote them before
the protocol moved into the package."""

from __future__ import annotations

from functools import partial
from pathlib import Path

from mmf_rl.compare import report
from mmf_rl.compare.bootstrap import build_table
from mmf_rl.compare.collect import Collected
from mmf_rl.compare.summary import paired_comparisons
from tests.compare.helpers import FIXED_BASES, FIXED_KINDS, PAPER_SUBSETS, PUSH_SUBSETS, fixed_errors

EXPECTED = Path(__file__).parent / "data" / "push_report_sections.md"


def test_the_sections_are_the_ones_benchmarks_accuracy_wrote():
    """``push_report_sections.md``: the part of results.md from the MSE table to the run times that
    benchmarks/accuracy.py's own markdown wrote before the move, for these per-window errors,
    coverages, KLs and timings."""
    table, episodes = build_table(
        fixed_errors(), FIXED_KINDS, PUSH_SUBSETS, lead=PAPER_SUBSETS, bases=FIXED_BASES
    )
    collected = Collected(
        coverage={
            "paper": (dict.fromkeys(PUSH_SUBSETS, 0.85), True),
            "LF-LSTM": ({"all": 0.7, "only_image": 0.9}, False),
        },
        intervals={
            "paper": {
                "coverage_50": dict.fromkeys(PUSH_SUBSETS, 0.48),
                "width_90": dict.fromkeys(PUSH_SUBSETS, 0.0123),
                "crps": dict.fromkeys(PUSH_SUBSETS, 0.2),
            },
            "LF-LSTM": {"coverage_50": {"all": 0.3}, "width_90": {}, "crps": {}},
        },
        kl={"paper": 1.234, "LF-LSTM": None},
    )
    measured = {
        "paper": {"ms_per_step": 50.0, "other_seconds": 4.0, "runs": 2, "batch_size": 32, "jobs": 1},
        "LF-LSTM": {"ms_per_step": 80.0, "other_seconds": 6.0, "runs": 2, "batch_size": 32, "jobs": 2},
    }
    reference = (
        "Reference: constant-velocity extrapolation of the object's past position (not a model input), "
        "MSE 0.5000; predicting the training mean gives about 1.\n\n"
    )
    text = report.results_sections(
        table,
        collected,
        paired_comparisons(table),
        partial(report.subset_title, modalities=("image", "force", "proprio")),
        report.episode_intervals_text(len(episodes)),
        reference,
    ) + report.run_time_section(3.0, measured)
    assert text == EXPECTED.read_text()


def test_subsets_are_titled_by_the_modalities_they_keep():
    title = partial(report.subset_title, modalities=("image", "force", "proprio"))
    assert title("without_proprio") == "image+force (without_proprio)"
    assert title("all") == "image+force+proprio"
    assert report.subset_title("only_b", ["c", "b", "a"]) == "b (only_b)"
    assert report.subset_title("without_b", ["c", "b", "a"]) == "c+a (without_b)"


def test_coverage_is_judged_against_the_band():
    text = report.coverage_table(
        {"paper": ({"all": 0.85, "only_image": 0.75}, True)}, ["all", "only_image"], title=str
    )
    assert text.splitlines()[-1] == "| paper | 0.850 | 0.750 | 1/2 | recalibrated on val |"


def test_interval_quality_tables_leave_out_entries_scored_before_a_metric():
    table, _ = build_table(fixed_errors(), FIXED_KINDS, PUSH_SUBSETS, lead=PAPER_SUBSETS, bases=FIXED_BASES)
    intervals = {
        "paper": {"coverage_50": {"all": 0.5}, "width_90": {"all": 0.25}, "crps": {}},
        "LF-LSTM": {"coverage_50": {}, "width_90": {}, "crps": {}},
    }
    text = report.interval_quality_section(intervals, table, title=str)
    assert "### CRPS" not in text and "LF-LSTM" not in text
    assert "| paper | 0.500 |" in text and "| paper | 0.25 |" in text
    empty = {"paper": {"coverage_50": {}, "width_90": {}, "crps": {}}}
    assert report.interval_quality_section(empty, table, title=str) == ""


def test_block_intervals_say_what_they_cover():
    text = report.intervals_text("block", [(4, 0), (4, 1)], [4], block=20)
    assert "over 2 blocks of 20 consecutive test windows" in text and "lower bound" in text
    assert report.intervals_text("episode", [1, 2, 3], [1, 2, 3], block=20).startswith(
        "Intervals: percentile bootstrap over the 3 test episodes (2000 resamples"
    )


def test_the_fit_section_sets_train_beside_test_and_is_left_out_without_scores():
    text = report.fit_section({"paper": {"train": 0.25, "test": 0.35}, "MulT (retrained)": None})
    assert text.startswith("## Fit: every sensor, training windows against test")
    assert "| paper | 0.2500 | 0.3500 | +0.1000 |" in text.splitlines()
    assert "MulT (retrained)" not in text
    assert report.fit_section({"paper": None}) == ""
