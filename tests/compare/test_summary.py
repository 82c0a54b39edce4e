"""mmf_rl.compare.summary: the summary lines (exactly as the benchmarks printed them before the
protocol moved into the package) and the paired comparisons."""

from __future__ import annotations

import re

import pytest

from mmf_rl.compare.bootstrap import Table, build_table, ordered_subsets
from mmf_rl.compare.summary import paired_comparisons, summarize, summarize_against_best_baseline
from tests.compare.helpers import (
    FIXED_BASES,
    FIXED_KINDS,
    PAPER_SUBSETS,
    PUSH_SUBSETS,
    cell,
    fixed_errors,
)

HUMANOID_SUBSETS = [
    "all",
    "without_cam_high",
    "without_state",
    "without_action",
    "only_cam_high",
    "only_state",
    "only_action",
]
AGAINST_BEST = re.compile(
    r"summary: all sensors paper MSE (\S+) vs best baseline (\S+) \((.+)\): paper/best = (\S+) "
    r"\(target <= 1\.05\); mean degradation without a sensor paper (\S+), best baseline (\S+)"
)


def test_the_push_summary_line_is_the_one_benchmarks_accuracy_printed():
    """The expected line was printed by benchmarks/accuracy.py's own summarize before the move, for
    these very per-window errors."""
    table, _ = build_table(fixed_errors(), FIXED_KINDS, PUSH_SUBSETS, lead=PAPER_SUBSETS, bases=FIXED_BASES)
    line, summary = summarize(table, PAPER_SUBSETS)
    assert line == (
        "summary: paper model best or tied in 7/7 subsets (zero-fill baselines), 0/3 paper subsets vs "
        "retrained; fusion spread 20%; mean degradation paper 52%, best baseline 52%"
    )
    assert summary["subsets_vs_zero_fill"] == 7 and summary["paper_subsets_vs_retrained"] == 3
    assert summary["fusion_spread"] == pytest.approx(0.2, abs=0.005)


def push_table(paper: float, zero_fill: float, retrained: float, fusion: float | None) -> Table:
    table = Table(subsets=ordered_subsets(PUSH_SUBSETS, PAPER_SUBSETS))
    rows = {
        "paper": ("paper", paper),
        "LF-LSTM": ("zero-fill", zero_fill),
        "LF-LSTM (retrained)": ("retrained", retrained),
    }
    if fusion is not None:
        rows["paper fusion=sum"] = ("fusion", fusion)
    for label, (kind, level) in rows.items():
        table.kinds[label] = kind
        table.cells[label] = {s: cell(level * (1 + 0.1 * i)) for i, s in enumerate(table.subsets)}
    return table


def test_summary_line_counts_wins_spread_and_degradations():
    line, summary = summarize(
        push_table(paper=0.30, zero_fill=0.305, retrained=0.2, fusion=0.36), PAPER_SUBSETS
    )
    # Each row degrades by 10% a subset step; the mean over the six subsets is 35% for every entry.
    assert line == (
        "summary: paper model best or tied in 7/7 subsets (zero-fill baselines), 0/3 paper subsets vs "
        "retrained; fusion spread 20%; mean degradation paper 35%, best baseline 35%"
    )
    assert (
        summary["best_or_tied_vs_zero_fill"] == 7 and summary["paper_subsets_best_or_tied_vs_retrained"] == 0
    )


def test_summary_line_says_what_the_run_lacks():
    table = push_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=None)
    del table.kinds["LF-LSTM (retrained)"], table.cells["LF-LSTM (retrained)"]
    line, summary = summarize(table, PAPER_SUBSETS)
    assert (
        "in 7/7 subsets" in line and "-/3 paper subsets vs retrained" in line and "fusion spread -;" in line
    )
    assert summary["fusion_spread"] is None


def test_best_baseline_degradation_ignores_rows_without_every_subset():
    table = push_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=None)
    for s in table.subsets[1:]:
        table.cells["LF-LSTM (retrained)"][s] = cell(0.2)  # 0% degradation...
    for s in table.subsets[3:]:
        del table.cells["LF-LSTM (retrained)"][s]  # ...but only on the paper's subsets
    line, summary = summarize(table, PAPER_SUBSETS)
    assert summary["best_baseline_mean_degradation"] == pytest.approx(0.35)
    assert "0/3 paper subsets vs retrained" in line and line.endswith("best baseline 35%")


def humanoid_table(levels: dict[str, tuple[str, float, dict[str, float]]]) -> Table:
    """``{label: (kind, all-sensor MSE, {subset: MSE / all-sensor MSE})}``; unlisted subsets: ratio 1.1."""
    table = Table(subsets=list(HUMANOID_SUBSETS))
    for label, (kind, level, ratios) in levels.items():
        table.kinds[label] = kind
        table.cells[label] = {
            s: cell(level * ratios.get(s, 1.0 if s == "all" else 1.1)) for s in HUMANOID_SUBSETS
        }
    return table


def test_against_best_baseline_compares_with_the_best_baseline_and_the_most_robust_one():
    without = ("without_cam_high", "without_state", "without_action")
    table = humanoid_table(
        {
            "paper": ("paper", 0.60, dict(zip(without, (1.02, 1.04, 1.06), strict=True))),
            "paper GRU vector encoders": ("variant", 0.40, {}),  # not a baseline
            "LF-LSTM": ("zero-fill", 0.57, dict(zip(without, (1.0, 1.9, 2.0), strict=True))),
            "MulT": ("zero-fill", 0.50, dict(zip(without, (1.1, 2.5, 2.4), strict=True))),
            "MVAE": ("zero-fill", 0.90, dict(zip(without, (1.0, 1.3, 1.2), strict=True))),
        }
    )
    line, summary = summarize_against_best_baseline(table, 1.05)
    assert line == (
        "summary: all sensors paper MSE 0.6000 vs best baseline 0.5000 (MulT): paper/best = 1.200 "
        "(target <= 1.05); mean degradation without a sensor paper 4%, best baseline 17%"
    )
    assert summary["best_baseline"] == "MulT" and summary["most_robust_baseline"] == "MVAE"
    assert summary["ratio_target_met"] is False
    # The only_* subsets (1.1 everywhere) do not enter the degradation without a sensor.
    assert summary["paper_mean_degradation_without_a_sensor"] == pytest.approx(0.04)
    assert summary["best_baseline_mean_degradation_without_a_sensor"] == pytest.approx(1 / 6)
    table.cells["paper"]["all"] = cell(0.52)
    assert summarize_against_best_baseline(table, 1.05)[1]["ratio_target_met"] is True


def test_against_best_baseline_says_what_the_run_lacks():
    table = humanoid_table({"paper": ("paper", 0.6, {}), "LF-LSTM": ("zero-fill", 0.5, {})})
    del table.cells["LF-LSTM"]["without_state"]  # a baseline without every subset has no mean degradation
    line, _ = summarize_against_best_baseline(table, 1.05)
    assert AGAINST_BEST.fullmatch(line), line
    assert "(LF-LSTM): paper/best = 1.200" in line and line.endswith("paper 10%, best baseline -")
    del table.kinds["LF-LSTM"], table.cells["LF-LSTM"]
    line, summary = summarize_against_best_baseline(table, 1.05)
    assert "vs best baseline - (-): paper/best = - (target" in line
    assert summary["ratio_target_met"] is None


def test_learned_prior_fusions_are_compared_with_their_base_not_the_default_model():
    table = push_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=0.30)
    learned = "paper prior=learned"
    rival = f"{learned}, fusion=sum"
    for label, kind, level in ((learned, "variant", 0.40), (rival, "learned fusion", 0.60)):
        table.kinds[label] = kind
        table.cells[label] = {s: cell(level) for s in table.subsets}
    table.bases[rival] = learned
    differences = paired_comparisons(table)["all"]
    assert differences[rival]["reference"] == learned
    assert differences[rival]["difference"] == pytest.approx(-0.20)
    assert differences["paper fusion=sum"]["reference"] == "paper"
    assert differences["LF-LSTM (retrained)"]["reference"] == "paper"
