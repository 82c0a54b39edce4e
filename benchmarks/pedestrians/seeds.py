"""Scores over training seeds: per model, mode and metric the mean over the seeds and their spread.

The spread is the range, max - min over the seeds: with three seeds a sample std is a poor estimate,
the range is what was seen. An average over scenes is aggregated from each seed's own average (its
spread is the spread of the per-seed averages, not an average of per-scene spreads).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from benchmarks.pedestrians.scoring import METRICS, MODES, Scores, ade_fde_text

SPREAD = "range: max - min over the seeds"
# model -> mode -> metric -> {"mean", "min", "max", "range"}
SeedStats = dict[str, dict[str, dict[str, dict[str, float]]]]


def spread(values: Sequence[float]) -> dict[str, float]:
    """``{mean, min, max, range}`` of one metric's values over the seeds."""
    low, high = float(np.min(values)), float(np.max(values))
    return {"mean": float(np.mean(values)), "min": low, "max": high, "range": high - low}


def over_seeds(per_seed: Mapping[int, Mapping[str, Scores]]) -> SeedStats:
    """``{model: {mode: {metric: spread}}}`` from ``{seed: {model: scores}}``: only the models scored
    with every seed."""
    seeds = list(per_seed)
    models = [m for m in per_seed[seeds[0]] if all(m in per_seed[s] for s in seeds)] if seeds else []
    return {
        model: {
            mode: {k: spread([per_seed[s][model][mode][k] for s in seeds]) for k in METRICS} for mode in MODES
        }
        for model in models
    }


def per_scene_over_seeds(per_seed: Mapping[int, Mapping[str, Mapping[str, Scores]]]) -> dict[str, SeedStats]:
    """``{scene: over_seeds}`` from ``{seed: {scene: {model: scores}}}``: the scenes of every seed."""
    seeds = list(per_seed)
    scenes = [s for s in per_seed[seeds[0]] if all(s in per_seed[seed] for seed in seeds)] if seeds else []
    return {scene: over_seeds({seed: per_seed[seed][scene] for seed in seeds}) for scene in scenes}


def statistic(stats: SeedStats, name: str) -> dict[str, Scores]:
    """``{model: {mode: {metric: stats' name}}}``: ``name`` one of mean, min, max, range."""
    return {
        model: {mode: {k: v[name] for k, v in metrics.items()} for mode, metrics in modes.items()}
        for model, modes in stats.items()
    }


def seeds_table(stats: SeedStats, deterministic: Sequence[str] = ()) -> str:
    """Markdown: one row per model, for each mode the mean ``minADE20/minFDE20`` and ``ADE/FDE`` over
    the seeds, each followed by its range in brackets (metres)."""
    mean, width = statistic(stats, "mean"), statistic(stats, "range")
    head = " | ".join(f"{mode} minADE20/minFDE20 | {mode} ADE/FDE" for mode in MODES)
    lines = [f"| model | {head} |", "|---" * (1 + 2 * len(MODES)) + "|"]
    for model in stats:
        mark = " †" if model in deterministic else ""
        cells = " | ".join(
            f"{ade_fde_text(mean[model][m], point)}{mark} ({ade_fde_text(width[model][m], point)})"
            for m in MODES
            for point in (False, True)
        )
        lines.append(f"| {model} | {cells} |")
    return "\n".join(lines)
