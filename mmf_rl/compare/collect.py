"""Read what the completed runs wrote: per-window errors, timings, coverage, the latent's KL and the fit
of the training windows."""

from __future__ import annotations

import json
import statistics
from dataclasses import dataclass, field

from mmf_rl.compare.bootstrap import EntryErrors
from mmf_rl.compare.entries import Entry, Study, run_plan
from mmf_rl.compare.runs import completed


def entry_results(entry: Entry, study: Study) -> tuple[dict[str, list[dict]], list[dict]]:
    """``({subset: [errors of each seed]}, [the entry's own runs' window_errors.json])``."""
    per_subset: dict[str, list[dict]] = {}
    runs = []
    for trained, _, run_dir, _, subset in run_plan(entry, study):
        result = completed(run_dir)
        if trained is entry:
            runs.append(result)
        for name, rows in result["subsets"].items():
            if subset in ("", name):
                per_subset.setdefault(name, []).append(rows)
    return per_subset, runs


def entry_coverage(entry: Entry, study: Study) -> tuple[dict[str, float], bool]:
    """``({subset: 90% interval coverage, mean over seeds}, every run recalibrated)`` from the
    evaluations ``run_one`` wrote (``<run>/eval/results.json``), with each run's scale as it stored it
    (recalibrated per presence pattern on val when its training did: ``mmf-rl train calibrate=true``)."""
    recalibrated = all(
        json.loads((run_dir / "eval" / "results.json").read_text()).get("scale_calibration") is not None
        for _, _, run_dir, _, _ in run_plan(entry, study)
    )
    return entry_metric(entry, study, "coverage_90"), recalibrated


def entry_metric(entry: Entry, study: Study, metric: str) -> dict[str, float]:
    """``{subset: metric, mean over seeds}`` of one metric of the evaluations' subset rows
    (``<run>/eval/results.json``); subsets where a run lacks it (written before it existed) are left
    out.

    Args:
        entry (Entry): the entry whose runs are read.
        study (Study): the comparison the runs belong to.
        metric (str): a key of the evaluation's subset rows, e.g. ``"width_90"``.

    Returns:
        ``{subset: mean over the runs that recorded it}``.
    """
    per_subset: dict[str, list[float]] = {}
    for _, _, run_dir, _, subset in run_plan(entry, study):
        scores = json.loads((run_dir / "eval" / "results.json").read_text())
        for name, row in scores["subsets"].items():
            if subset in ("", name) and row.get(metric) is not None:
                per_subset.setdefault(name, []).append(row[metric])
    return {name: statistics.fmean(values) for name, values in per_subset.items()}


# Beside the 90% coverage: the 50% coverage, and the sharpness and proper score that tell a
# wider-and-therefore-covered interval from a good one.
INTERVAL_METRICS = ("coverage_50", "width_90", "crps")


def entry_kl(entry: Entry, study: Study) -> float | None:
    """The KL of the posterior to the prior in nats with every sensor, mean over seeds (``None`` for a
    model without a latent): near zero, the latent has collapsed."""
    values = []
    for _, _, run_dir, _, subset in run_plan(entry, study):
        row = json.loads((run_dir / "eval" / "results.json").read_text())["subsets"].get("all", {})
        if subset in ("", "all") and row.get("kl") is not None:
            values.append(row["kl"])
    return statistics.fmean(values) if values else None


def entry_fit(entry: Entry, study: Study) -> dict[str, float] | None:
    """``{"train", "test"}``: the entry's MSE with every sensor on training windows and on the test split,
    mean over seeds; ``None`` when a run predates the training-window score or the entry is only
    trained per subset (the retrained baselines)."""
    train, test = [], []
    for trained, _, run_dir, _, subset in run_plan(entry, study):
        result = completed(run_dir)
        if trained is not entry or subset not in ("", "all"):
            continue
        if result.get("train_mse") is None or "all" not in result["subsets"]:
            return None
        train.append(result["train_mse"])
        test.append(statistics.fmean(result["subsets"]["all"]["squared_error"]))
    return {"train": statistics.fmean(train), "test": statistics.fmean(test)} if train else None


def timing(runs: dict[str, list[dict]]) -> dict[str, dict[str, float]]:
    """Per entry: measured ms per training step (the training loop), the rest of a run (data and model
    setup, validation, checkpoint, evaluation) in seconds, and how many runs were trained at once while
    they were measured (``jobs``; results written before it was recorded count as 1).

    Args:
        runs (dict[str, list[dict]]): each entry's runs' ``window_errors.json`` results.

    Returns:
        ``{label: {"ms_per_step", "other_seconds", "runs", "batch_size", "jobs"}}`` for the entries with
        runs.
    """
    out = {}
    for label, results in runs.items():
        if results:
            out[label] = {
                "ms_per_step": 1e3 * statistics.fmean(r["step_seconds"] for r in results),
                "other_seconds": statistics.fmean(
                    r["seconds"] - r["steps"] * r["step_seconds"] for r in results
                ),
                "runs": len(results),
                "batch_size": results[0]["batch_size"],
                "jobs": statistics.fmean(r.get("jobs", 1) for r in results),
            }
    return out


@dataclass
class Collected:
    """Everything the report reads, per entry label.

    Args:
        errors (EntryErrors, optional): ``{label: {subset: [each seed's rows]}}``.
        runs (dict[str, list[dict]], optional): the entry's own runs' results.
        kinds (dict[str, str], optional): each entry's kind.
        bases (dict[str, str], optional): each entry's base's label, where it has one.
        coverage (dict[str, tuple[dict[str, float], bool]], optional): ``({subset: 90% coverage}, every
            run recalibrated)``.
        intervals (dict[str, dict[str, dict[str, float]]], optional): ``{metric: {subset: value}}``
            for each of :data:`INTERVAL_METRICS` (50% coverage, 90% width, CRPS).
        kl (dict[str, float | None], optional): the latent's KL with every sensor (``None``: no latent).
        fit (dict[str, dict[str, float] | None], optional): ``{"train", "test"}`` MSE.
    """

    errors: EntryErrors = field(default_factory=dict)
    runs: dict[str, list[dict]] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)
    bases: dict[str, str] = field(default_factory=dict)
    coverage: dict[str, tuple[dict[str, float], bool]] = field(default_factory=dict)
    intervals: dict[str, dict[str, dict[str, float]]] = field(default_factory=dict)
    kl: dict[str, float | None] = field(default_factory=dict)
    fit: dict[str, dict[str, float] | None] = field(default_factory=dict)

    def constant_velocity_mse(self) -> float | None:
        """The constant-velocity reference's MSE some run recorded (``None``: none did)."""
        return next(
            (
                r["constant_velocity"]["mse"]
                for rs in self.runs.values()
                for r in rs
                if r.get("constant_velocity")
            ),
            None,
        )


def collect_runs(study: Study) -> Collected:
    """Read what the completed runs of every entry wrote.

    Args:
        study (Study): the comparison; every run it plans must be complete.

    Returns:
        The collected results.
    """
    out = Collected()
    for entry in study.entries:
        out.errors[entry.label], out.runs[entry.label] = entry_results(entry, study)
        out.kinds[entry.label] = entry.kind
        if entry.base is not None:
            out.bases[entry.label] = entry.base.label
        out.coverage[entry.label] = entry_coverage(entry, study)
        out.intervals[entry.label] = {m: entry_metric(entry, study, m) for m in INTERVAL_METRICS}
        out.kl[entry.label] = entry_kl(entry, study)
        out.fit[entry.label] = entry_fit(entry, study)
    return out
