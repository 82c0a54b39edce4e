"""The comparison's verdicts: paired differences against the paper model and the one-line summaries."""

from __future__ import annotations

import statistics
from collections.abc import Sequence

from mmf_rl.compare.bootstrap import Table, difference_interval
from mmf_rl.compare.entries import BASELINE_KINDS, TRAINED_FOR_MISSING_KIND


def percent(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def summarize(
    table: Table, headline: Sequence[str], headline_name: str = "paper subsets"
) -> tuple[str, dict]:
    """The paper-table line: where the paper model is best or tied against the zero-fill baselines (every
    subset), the baselines trained for missing sensors (every subset; said only when some ran), the
    retrained ones (the ``headline`` subsets), the fusion ablations' spread, and the mean
    degradations. ``-`` where the table lacks the entries a number needs.

    Args:
        table (Table): the comparison's table, with a ``"paper"`` entry.
        headline (Sequence[str]): the subsets the retrained baselines are compared on.
        headline_name (str, optional): what the line calls them. Defaults to ``"paper subsets"``.

    Returns:
        ``(line, numbers)``: the ``summary: ...`` line and the figures in it, by name.
    """
    won, compared = table.wins(("zero-fill",), table.subsets)
    retrained_won, retrained_compared = table.wins(("retrained",), headline)
    spread = table.fusion_spread()
    # Mean degradations compare like with like: only baselines scored on every subset (retrained ones
    # may be trained for the headline subsets only).
    baselines = [
        label for label in table.labels(*BASELINE_KINDS) if set(table.cells[label]) == set(table.subsets)
    ]
    paper_deg = table.mean_degradation("paper")
    best_baseline_deg = min((table.mean_degradation(label) for label in baselines), default=None)
    robust_won, robust_compared = table.wins((TRAINED_FOR_MISSING_KIND,), table.subsets)
    # Said only where such baselines ran: the line of a comparison without them keeps its form.
    robust = (
        f"{robust_won}/{robust_compared} subsets (baselines trained for missing sensors), "
        if robust_compared
        else ""
    )
    line = (
        f"summary: paper model best or tied in {won if compared else '-'}/{compared} subsets "
        f"(zero-fill baselines), {robust}"
        f"{retrained_won if retrained_compared else '-'}/{len(headline)} {headline_name} vs retrained; "
        f"fusion spread {percent(spread)}; "
        f"mean degradation paper {100 * paper_deg:.0f}%, best baseline {percent(best_baseline_deg)}"
    )
    return line, {
        "best_or_tied_vs_zero_fill": won,
        "subsets_vs_zero_fill": compared,
        "best_or_tied_vs_trained_for_missing": robust_won,
        "subsets_vs_trained_for_missing": robust_compared,
        "paper_subsets_best_or_tied_vs_retrained": retrained_won,
        "paper_subsets_vs_retrained": retrained_compared,
        "fusion_spread": spread,
        "paper_mean_degradation": paper_deg,
        "best_baseline_mean_degradation": best_baseline_deg,
    }


def without_subsets(table: Table) -> list[str]:
    return [s for s in table.subsets if s.startswith("without_")]


def mean_degradation_without_a_sensor(table: Table, label: str) -> float | None:
    """Mean relative MSE increase over the ``without_<sensor>`` subsets (None if one is not scored)."""
    subsets = without_subsets(table)
    if not subsets or any(s not in table.cells[label] for s in subsets) or "all" not in table.cells[label]:
        return None
    return statistics.fmean(table.degradation(label, s) for s in subsets)


def summarize_against_best_baseline(table: Table, target_ratio: float) -> tuple[str, dict]:
    """The line for the paper model against zero-fill baselines: its all-sensor MSE over the best
    baseline's (the target: at most ``target_ratio``), and its mean degradation without one sensor
    against the most robust baseline's.

    Args:
        table (Table): the comparison's table, with a ``"paper"`` entry.
        target_ratio (float): the paper model's all-sensor MSE over the best baseline's it should stay
            under.

    Returns:
        ``(line, numbers)``: the ``summary: ...`` line and the figures in it, by name.
    """
    baselines = [label for label in table.labels("zero-fill") if "all" in table.cells[label]]
    paper = table.cells["paper"]["all"].mean
    best = min(baselines, key=lambda label: table.cells[label]["all"].mean, default=None)
    best_mse = None if best is None else table.cells[best]["all"].mean
    ratio = None if best_mse is None else paper / best_mse
    paper_deg = mean_degradation_without_a_sensor(table, "paper")
    baseline_degs = {
        label: d for label in baselines if (d := mean_degradation_without_a_sensor(table, label)) is not None
    }
    robust = min(baseline_degs, key=baseline_degs.get, default=None)
    line = (
        f"summary: all sensors paper MSE {paper:.4f} vs best baseline "
        f"{'-' if best_mse is None else f'{best_mse:.4f}'} ({best or '-'}): "
        f"paper/best = {'-' if ratio is None else f'{ratio:.3f}'} (target <= {target_ratio}); "
        f"mean degradation without a sensor paper {percent(paper_deg)}, "
        f"best baseline {percent(None if robust is None else baseline_degs[robust])}"
    )
    return line, {
        "paper_all_mse": paper,
        "best_baseline": best,
        "best_baseline_all_mse": best_mse,
        "paper_over_best": ratio,
        "target_ratio": target_ratio,
        "ratio_target_met": None if ratio is None else ratio <= target_ratio,
        "paper_mean_degradation_without_a_sensor": paper_deg,
        "most_robust_baseline": robust,
        "best_baseline_mean_degradation_without_a_sensor": baseline_degs.get(robust),
    }


def reference_of(table: Table, label: str) -> str:
    """The entry a rival is compared with: ``paper``, or for a learned-prior fusion ablation the learned
    prior with the paper's fusion (its base)."""
    return table.bases[label] if table.kinds[label] == "learned fusion" else "paper"


def paired_comparisons(table: Table) -> dict[str, dict[str, dict]]:
    """Per subset: ``reference - rival`` intervals (paired) of each baseline against the paper model and
    of each fusion ablation against the same model with the paper's fusion (``reference_of``).

    Args:
        table (Table): the comparison's table.

    Returns:
        ``{subset: {rival: {"reference", "difference", "low", "high"}}}``: the reference's label, its
        MSE minus the rival's, and that difference's interval.
    """
    out: dict[str, dict[str, dict]] = {}
    for s in table.subsets:
        for label in table.labels(*BASELINE_KINDS, "fusion", "learned fusion"):
            reference = reference_of(table, label)
            ours = table.cells.get(reference, {}).get(s)
            if ours is not None and s in table.cells[label]:
                low, high = difference_interval(ours, table.cells[label][s])
                out.setdefault(s, {})[label] = {
                    "reference": reference,
                    "difference": ours.mean - table.cells[label][s].mean,
                    "low": low,
                    "high": high,
                }
    return out
