"""The comparison as markdown: MSE tables with paired intervals, degradations, fusion verdicts,
coverage, the latent's KL, the fit of the training windows and run times; and its results.json cells."""

from __future__ import annotations

from collections.abc import Callable, Sequence

from mmf_rl.compare.bootstrap import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    LEVEL,
    MIN_EPISODES,
    Cell,
    Table,
    overlap,
)
from mmf_rl.compare.collect import Collected
from mmf_rl.compare.entries import BASELINE_KINDS
from mmf_rl.compare.runs import FIT_WINDOWS
from mmf_rl.compare.summary import reference_of

# The forecast's 90% interval should cover this share of the test futures in every subset.
COVERAGE_TARGET = (0.80, 0.97)

Title = Callable[[str], str]


def subset_title(name: str, modalities: Sequence[str]) -> str:
    """``without_b`` of modalities ``a, b, c`` -> ``a+c (without_b)``; ``all`` -> ``a+b+c``, the kept
    modalities in the order given."""
    from mmf_rl.compare.entries import subsets

    kept = dict(subsets(sorted(modalities)))[name]
    return "+".join(m for m in modalities if kept[m]) + ("" if name == "all" else f" ({name})")


def cell_text(cell: Cell | None, bold: bool, tied: bool) -> str:
    if cell is None:
        return ""
    text = f"{cell.mean:.4f} [{cell.low:.4f}, {cell.high:.4f}]"
    return f"**{text}**" if bold else f"{text} =" if tied else text


def differences_text(differences: dict[str, dict]) -> str:
    """``label: difference [low, high]; ...`` of paired differences (``paired_comparisons``' cells)."""
    return "; ".join(
        f"{label}: {c['difference']:+.4f} [{c['low']:+.4f}, {c['high']:+.4f}]"
        for label, c in differences.items()
    )


def fusion_verdicts(table: Table, differences: dict[str, dict]) -> str:
    """One paragraph per prior: the paired all-modality differences against the attention fusion and
    whether attention beats every other fusion beyond the interval (Table 4's claim)."""
    text = ""
    for kind in ("fusion", "learned fusion"):
        rivals = {label: c for label, c in differences.items() if table.kinds[label] == kind}
        if rivals:
            reference = next(iter(rivals.values()))["reference"]
            beats = all(c["high"] < 0 for c in rivals.values())
            text += (
                f"Paired difference {reference} - fusion ablation, all modalities: "
                + differences_text(rivals)
                + ". Attention better than every other fusion beyond the interval: "
                + f"{'yes' if beats else 'no'}.\n\n"
            )
    return text


def mse_table(table: Table, labels: list[str], contenders: list[str], title: Title) -> str:
    """Subsets as rows (named by ``title``), entries as columns, each entry's protocol (its kind) first;
    bold: best of ``contenders``, ``=``: any entry tied with it."""
    lines = [
        "| subset | " + " | ".join(labels) + " |",
        "|---" * (len(labels) + 1) + "|",
        "| *protocol* | " + " | ".join(table.kinds.get(label, "") for label in labels) + " |",
    ]
    for s in table.subsets:
        present = {label: table.cells[label][s] for label in contenders if s in table.cells[label]}
        best = min(present, key=lambda label: present[label].mean) if present else None
        cells = [
            cell_text(
                table.cells[label].get(s),
                label == best,
                best is not None
                and s in table.cells[label]
                and overlap(table.cells[label][s], present[best]),
            )
            for label in labels
        ]
        lines.append(f"| {title(s)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def degradation_table(table: Table, labels: list[str], title: Title) -> str:
    lines = ["| subset | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    for s in table.subsets[1:]:
        lines.append(
            f"| {title(s)} | "
            + " | ".join(
                f"{100 * table.degradation(label, s):+.0f}%" if s in table.cells[label] else ""
                for label in labels
            )
            + " |"
        )
    lines.append(
        "| mean | " + " | ".join(f"{100 * table.mean_degradation(label):+.0f}%" for label in labels) + " |"
    )
    return "\n".join(lines)


def coverage_table(
    coverage: dict[str, tuple[dict[str, float], bool]], subsets: Sequence[str], title: Title
) -> str:
    """Entries as rows: the 90% coverage per subset, how many subsets are in ``COVERAGE_TARGET``, and
    whether the scale was recalibrated."""
    low, high = COVERAGE_TARGET
    lines = [
        "| entry | " + " | ".join(title(s) for s in subsets) + f" | in {low:.2f}-{high:.2f} | scale |",
        "|---" * (len(subsets) + 3) + "|",
    ]
    for label, (cells, recalibrated) in coverage.items():
        inside = sum(low <= cells[s] <= high for s in subsets if s in cells)
        lines.append(
            f"| {label} | "
            + " | ".join(f"{cells[s]:.3f}" if s in cells else "" for s in subsets)
            + f" | {inside}/{sum(s in cells for s in subsets)} | "
            + ("recalibrated on val" if recalibrated else "as trained")
            + " |"
        )
    return "\n".join(lines)


def kl_section(kl: dict[str, float | None]) -> str:
    rows = [f"| {label} | {value:.2f} |" for label, value in kl.items() if value is not None]
    if not rows:
        return ""
    return (
        "## Latent: KL(q(z|X[,y]) || p(z|X)) on test, every sensor (nats, mean over seeds)\n\n"
        "What the latent carries beyond its prior; near zero it has collapsed and a forecast does not "
        "depend on it.\n\n| entry | KL |\n|---|---|\n" + "\n".join(rows) + "\n\n"
    )


def fit_section(fit: dict[str, dict[str, float] | None]) -> str:
    rows = [
        f"| {label} | {f['train']:.4f} | {f['test']:.4f} | {f['test'] - f['train']:+.4f} |"
        for label, f in fit.items()
        if f is not None
    ]
    if not rows:
        return ""
    return (
        "## Fit: every sensor, training windows against test (normalised MSE, mean over seeds)\n\n"
        f"Train: up to {FIT_WINDOWS} training windows drawn once, the same for every run. A model behind "
        "on test and behind on train does not fit its data; one behind on test only does not "
        "generalise.\n\n| entry | train | test | test - train |\n|---|---|---|---|\n"
        + "\n".join(rows)
        + "\n\n"
    )


def coverage_section(coverage: dict[str, tuple[dict[str, float], bool]], table: Table, title: Title) -> str:
    if not coverage:
        return ""
    return (
        "## Calibration: 90% interval coverage on test (mean over seeds)\n\n"
        f"Target: {COVERAGE_TARGET[0]:.2f}-{COVERAGE_TARGET[1]:.2f} in every subset. The "
        "paper model and its variants are scored at their eval latent (default: the prior's mean).\n\n"
        + coverage_table(coverage, table.subsets, title)
        + "\n\n"
    )


INTERVAL_TABLES = (
    ("coverage_50", "50% interval coverage (target 0.50)", "{:.3f}"),
    ("width_90", "90% interval mean width (target units)", "{:.3g}"),
    ("crps", "CRPS (normalised; lower is better)", "{:.4f}"),
)


def interval_quality_section(
    intervals: dict[str, dict[str, dict[str, float]]], table: Table, title: Title
) -> str:
    """The 50% coverage, the 90% intervals' width and the CRPS per entry and subset: of two entries
    that cover alike, the narrower one with the lower CRPS is the better forecaster of its
    uncertainty. Entries whose runs predate a metric are left out of its table.

    Args:
        intervals (dict[str, dict[str, dict[str, float]]]): ``Collected.intervals``.
        table (Table): the MSE table, for its subsets.
        title (Title): a subset's column title.

    Returns:
        The markdown section, or ``""`` when no entry recorded any of the metrics.
    """
    parts = []
    for metric, heading, fmt in INTERVAL_TABLES:
        rows = [
            f"| {label} | " + " | ".join(fmt.format(c[s]) if s in c else "" for s in table.subsets) + " |"
            for label, metrics in intervals.items()
            if (c := metrics.get(metric))
        ]
        if rows:
            parts.append(
                f"### {heading}\n\n| entry | "
                + " | ".join(title(s) for s in table.subsets)
                + " |\n"
                + "|---" * (len(table.subsets) + 1)
                + "|\n"
                + "\n".join(rows)
                + "\n\n"
            )
    if not parts:
        return ""
    return (
        "## Intervals: sharpness and a proper score on test (mean over seeds)\n\n"
        "Coverage alone rewards width: a wide enough interval covers everything. The width and the "
        "CRPS say what the coverage costs.\n\n" + "".join(parts)
    )


def episode_intervals_text(test_episodes: int) -> str:
    return (
        f"Intervals: percentile bootstrap over the {test_episodes} test episodes "
        f"({BOOTSTRAP_RESAMPLES} resamples, one generator seeded {BOOTSTRAP_SEED}, "
        "the same resamples for every entry, seed and subset); "
        "they cover test-set sampling, not seed variation (per-seed values in results.json). "
        "Bold: lowest mean among the paper model and the baselines; "
        "`=`: interval overlaps the bold one (tied).\n\n"
    )


def mse_sections(table: Table, title: Title, intervals: str, reference: str) -> str:
    """The main MSE table (paper model, variants, baselines) and the ablation tables."""
    main_labels = table.labels("paper", "variant", *BASELINE_KINDS)
    ablation_labels = ["paper", *table.labels("fusion", "ablation")]
    text = (
        f"## Test MSE (normalised target): mean over seeds [{LEVEL:.0%} interval]\n\n"
        + intervals
        + mse_table(table, main_labels, table.labels("paper", *BASELINE_KINDS), title)
        + "\n\n"
        + reference
    )
    if len(ablation_labels) > 1:
        text += (
            "## Ablations of the paper model (Tables 4, 5)\n\n"
            "Bold: lowest mean of the row; `=`: tied with it.\n\n"
            + mse_table(table, ablation_labels, ablation_labels, title)
            + "\n\n"
        )
    learned_fusion = table.labels("learned fusion")
    if learned_fusion:
        learned_labels = [reference_of(table, learned_fusion[0]), *learned_fusion]
        text += (
            "## Table 4 under the learned prior\n\n"
            "With the standard prior a forecast is decoded at z = 0, so the fusion acts only in training; "
            "with the learned prior it gives p(z|X), which every forecast is decoded from.\n\n"
            + mse_table(table, learned_labels, learned_labels, title)
            + "\n\n"
        )
    return text


def results_sections(
    table: Table,
    collected: Collected,
    comparisons: dict,
    title: Title,
    intervals: str,
    reference: str = "",
) -> str:
    """Everything between a report's header and its run times: MSE, ablations, degradation, fusion
    verdicts, coverage, the latent's KL and the fit of the training windows."""
    labels = [
        *table.labels("paper", "variant", *BASELINE_KINDS),
        *table.labels("fusion", "ablation"),
        *table.labels("learned fusion"),
    ]
    return (
        mse_sections(table, title, intervals, reference)
        + "## Relative degradation (MSE / MSE with all modalities - 1)\n\n"
        + degradation_table(table, labels, title)
        + "\n\n"
        + fusion_verdicts(table, comparisons.get("all", {}))
        + coverage_section(collected.coverage, table, title)
        + interval_quality_section(collected.intervals, table, title)
        + kl_section(collected.kl)
        + fit_section(collected.fit)
    )


def run_time_section(cache_seconds: float, measured: dict[str, dict[str, float]]) -> str:
    return (
        "## Run time\n\n"
        f"Window cache built or opened once before the trainings in {cache_seconds:.0f} s. "
        "Per entry, measured by each run when it trained (a reused run keeps its times): the training "
        "loop's time per step and the rest of a run (data and model setup, validation, checkpoint, "
        "evaluation).\n\n"
        "| entry | runs timed | runs at once | training ms/step | rest of a run (s) "
        "|\n|---|---|---|---|---|\n"
        + "\n".join(
            f"| {label} | {m['runs']} | {m['jobs']:g} | {m['ms_per_step']:.0f} | {m['other_seconds']:.0f} |"
            for label, m in measured.items()
        )
        + "\n\n"
    )


def cells_json(table: Table) -> dict:
    return {label: {s: c.to_dict() for s, c in cells.items()} for label, cells in table.cells.items()}


def tables_json(table: Table, collected: Collected, comparisons: dict, measured: dict) -> dict:
    """What the report's tables show, for a results.json: the subsets, every cell, the paired
    differences, the run times, the coverage, the latent's KL and the fit."""
    return {
        "subsets": table.subsets,
        "cells": cells_json(table),
        "paired_differences": comparisons,
        "timing": measured,
        "coverage_90": {label: cells for label, (cells, _) in collected.coverage.items()},
        "intervals": collected.intervals,
        "kl": collected.kl,
        "fit": collected.fit,
    }


def intervals_text(unit: str, groups: list, test_episodes: list[int], block: int) -> str:
    """What the intervals resample: test episodes, or (too few of them) blocks of ``block`` windows."""
    resampling = (
        f"percentile bootstrap over the {len(groups)} test episodes"
        if unit == "episode"
        else f"percentile bootstrap over {len(groups)} blocks of {block} consecutive test windows "
        f"(one window's span, H + T frames) of the {len(test_episodes)} test episode(s) "
        f"{test_episodes}: fewer than {MIN_EPISODES} test episodes make an episode bootstrap meaningless. "
        "The interval covers the variation over stretches of this test motion, not over episodes, "
        "operators or recordings: read it as a lower bound on the uncertainty"
    )
    return (
        f"Intervals: {resampling} ({BOOTSTRAP_RESAMPLES} resamples, one generator seeded "
        f"{BOOTSTRAP_SEED}, the same resamples for every entry, seed and subset); they do not cover "
        "seed variation (per-seed values in results.json). Bold: lowest mean among the paper model and "
        "the baselines; `=`: interval overlaps the bold one (tied)."
    )
