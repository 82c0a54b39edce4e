"""Evaluation results as files: ``results.json``, ``results.md`` (the paper's Table 3 layout), plots."""

from __future__ import annotations

import json
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only: no display on training machines
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

COLUMNS = [
    ("windows", "windows", "{:.0f}"),
    ("windows_available", "available", "{:.0f}"),
    ("mse", "MSE (norm.)", "{:.4f}"),
    ("mse_units", "MSE", "{:.3g}"),
    ("ade", "ADE", "{:.4g}"),
    ("fde", "FDE", "{:.4g}"),
    ("min_mse_k", "minMSE@K (norm.)", "{:.4f}"),
    ("min_ade_k", "minADE@K", "{:.4g}"),
    ("min_fde_k", "minFDE@K", "{:.4g}"),
    ("nll", "NLL", "{:.3f}"),
    ("coverage_50", "cover 50%", "{:.2f}"),
    ("coverage_90", "cover 90%", "{:.2f}"),
    ("width_90", "width 90%", "{:.3g}"),
    ("crps", "CRPS (norm.)", "{:.4f}"),
    ("kl", "KL (nats)", "{:.2f}"),
    ("degradation", "MSE vs all", "{:+.1%}"),
]


def write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically: readers see the old file or the new one, never half."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_json(path: Path, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True))


def markdown_table(
    results: dict[str, dict[str, float]],
    baseline: dict[str, float] | None,
    units: str = "target units",
    num_samples: int | None = None,
) -> str:
    """One row per presence subset (+ the constant-velocity baseline), one column per metric."""
    columns = [c for c in COLUMNS if any(c[0] in r for r in results.values())]
    lines = [
        "| subset | " + " | ".join(title for _, title, _ in columns) + " |",
        "|---" * (len(columns) + 1) + "|",
    ]
    for subset, metrics in results.items():
        cells = [fmt.format(metrics[key]) if key in metrics else "" for key, _, fmt in columns]
        lines.append(f"| {subset} | " + " | ".join(cells) + " |")
    if baseline:
        cells = [fmt.format(baseline[key]) if key in baseline else "" for key, _, fmt in columns]
        lines.append("| constant velocity | " + " | ".join(cells) + " |")
    k = f"K = {num_samples}" if num_samples else "K"
    lines.append("")
    lines.append(
        f"MSE (norm.) and CRPS (norm.) are on the normalised target; MSE, ADE, FDE and 'width 90%' are "
        f"in {units}. The min@K columns take each minimum on its own over {k} forecasts decoded from "
        "prior samples; the other columns score the point forecast (a latent model's forecast by its "
        "eval_latent; by default the decode of the prior's mean). 'cover p%' is the share of target "
        "values inside the forecast's central p% interval (calibrated: p%; with a level curve, the "
        "curve's); 'width 90%' is the mean width of the 90% intervals, and CRPS the forecast's "
        "continuous ranked probability score (lower is better): a wider interval covers more without "
        "being better. Rows "
        "are paired: each is averaged over the same 'windows', those where every row keeps a present "
        "modality; 'available' is how many windows the row alone could be scored on. 'MSE vs all' "
        "is the relative change of MSE (norm.) against all modalities present, on those windows."
    )
    return "\n".join(lines) + "\n"


def constant_velocity_warning(
    results: dict[str, dict[str, float]], baseline: dict[str, float] | None, relative: bool
) -> str | None:
    """The warning for a model whose MSE with all modalities is worse than constant velocity's (on
    the same windows), with the likely fix for an absolute target; ``None`` when it is not."""
    if not baseline or "all" not in results or results["all"]["mse"] <= baseline["mse"]:
        return None
    model, cv = results["all"]["mse"], baseline["mse"]
    fix = (
        " The target is absolute: forecasting its change from the last observed frame usually fixes this "
        "(retrain with data.target.relative=true)."
        if not relative
        else " Train longer, or check the inputs (mmf-rl inspect DATASET)."
    )
    return (
        f"the model loses to constant velocity: MSE (norm.) with all modalities {model:.4g} against "
        f"constant velocity's {cv:.4g} ({model / cv:.2f}x) on the same windows.{fix}"
    )


def plot_error_per_subset(
    results: dict[str, dict[str, float]], baseline: dict[str, float] | None, path: Path
) -> None:
    names = list(results)
    fig, ax = plt.subplots(figsize=(max(5, 1.1 * len(names)), 3.5))
    ax.bar(names, [results[n]["mse"] for n in names], color="tab:blue")
    if baseline:
        ax.axhline(baseline["mse"], color="tab:red", linestyle="--", label="constant velocity")
        ax.legend()
    ax.set_ylabel("MSE (normalised)")
    ax.set_title("forecast error per presence subset")
    ax.tick_params(axis="x", rotation=30)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_forecasts(examples: dict[str, dict[str, torch.Tensor]], path: Path, units: str) -> None:
    """Per subset (rows) and window (columns): past, truth, mean forecast and samples.

    A 2-D target is drawn as a trajectory in its plane; otherwise each dim over time.
    """
    subsets = list(examples)
    num_windows = examples[subsets[0]]["target"].shape[0]
    fig, axes = plt.subplots(
        len(subsets), num_windows, figsize=(3.2 * num_windows, 2.8 * len(subsets)), squeeze=False
    )
    for row, subset in enumerate(subsets):
        ex = examples[subset]
        for col in range(num_windows):
            ax = axes[row][col]
            target, mean = ex["target"][col], ex["mean"][col]
            samples = ex["samples"][col] if ex.get("samples") is not None else []
            past = ex["past"][col] if ex.get("past") is not None else None
            if target.shape[-1] == 2:
                for s in samples:
                    ax.plot(s[:, 0], s[:, 1], color="tab:orange", alpha=0.25, linewidth=0.8)
                if past is not None:
                    ax.plot(past[:, 0], past[:, 1], "k.-", linewidth=1, markersize=3, label="past")
                ax.plot(target[:, 0], target[:, 1], "g.-", linewidth=1.5, markersize=3, label="truth")
                ax.plot(mean[:, 0], mean[:, 1], "b.-", linewidth=1.5, markersize=3, label="forecast")
                ax.set_aspect("equal", adjustable="datalim")
            else:
                steps = torch.arange(1, target.shape[0] + 1)
                for s in samples:
                    ax.plot(steps, s[:, 0], color="tab:orange", alpha=0.25, linewidth=0.8)
                ax.plot(steps, target[:, 0], "g.-", label="truth (dim 0)")
                ax.plot(steps, mean[:, 0], "b.-", label="forecast (dim 0)")
            if row == 0 and col == 0:
                ax.legend(fontsize=7)
            if col == 0:
                ax.set_ylabel(subset, fontsize=9)
            ax.tick_params(labelsize=7)
    fig.suptitle(f"forecasts vs ground truth ({units}); orange: samples from the prior", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_latent_tsne(latents: dict[str, torch.Tensor], path: Path, seed: int = 0) -> None:
    """t-SNE of the latents the test-time forecasts were decoded from, coloured by presence subset
    (the paper's latent-space figure; for a learned prior these are its means)."""
    from sklearn.manifold import TSNE

    names = [n for n, z in latents.items() if len(z)]
    stacked = torch.cat([latents[n] for n in names]).numpy()
    labels = [n for n in names for _ in range(len(latents[n]))]
    perplexity = max(2.0, min(30.0, (len(stacked) - 1) / 3))
    embedded = TSNE(n_components=2, perplexity=perplexity, random_state=seed, init="pca").fit_transform(
        stacked
    )
    fig, ax = plt.subplots(figsize=(5.5, 4.5))
    for name in names:
        mask = [label == name for label in labels]
        ax.scatter(embedded[mask, 0], embedded[mask, 1], s=6, alpha=0.6, label=name)
    ax.legend(fontsize=7, markerscale=2)
    ax.set_title("t-SNE of test-time latents by presence subset")
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
