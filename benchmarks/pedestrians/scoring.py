"""Human-trajectory scoring as the ETH/UCY literature reports it: the four test modes, a model scored
in them on a split, constant velocity with its heading noise picked on val, per-scene and average
tables in metres, the published reference table, forecasts drawn on a scene image.

A mode is a presence subset over the trajectory data's modalities: ``all``, ``without_scene``,
``without_neighbours`` and ``trajectory_only``. Every model is scored in every mode on the same
test windows (:func:`~mmf_rl.eval.metrics.evaluate_presence_subsets`); ADE/FDE are those of the
point forecast, minADE20/minFDE20 the per-agent minimum over 20 samples.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")  # files only: no display on training machines
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402

from mmf_rl import keys  # noqa: E402
from mmf_rl.eval.metrics import evaluate_presence_subsets  # noqa: E402
from mmf_rl.models import build_model  # noqa: E402

if TYPE_CHECKING:
    from mmf_rl.datasets import WindowDataset
    from mmf_rl.datasets.ethucy import Scene

logger = logging.getLogger(__name__)

MODES = {
    "all": {"trajectory": True, "neighbours": True, "scene": True},
    "without_scene": {"trajectory": True, "neighbours": True, "scene": False},
    "without_neighbours": {"trajectory": True, "neighbours": False, "scene": True},
    "trajectory_only": {"trajectory": True, "neighbours": False, "scene": False},
}
METRICS = {"ade": "ADE", "fde": "FDE", "min_ade_k": "minADE20", "min_fde_k": "minFDE20"}
NUM_SAMPLES = 20
# minADE20 / minFDE20 in metres, average of the five scenes (leak-free versions): method, value, the
# window set it is scored on (`mmf_rl.datasets.ethucy.WINDOW_SETS`, from its published data loader;
# "not checked": no ETH/UCY loader of its own is published, PECNet's and LED's repositories have none),
# source.
PUBLISHED = (
    (
        "constant velocity (deterministic)",
        "0.52 / 1.14",
        "social_gan",
        "Schöller et al. 2020; re-measured on these files",
    ),
    ("Social-GAN (20V-20)", "0.61 / 1.21", "social_gan", "Gupta et al. 2018, Table 1"),
    ("Social-STGCNN", "0.44 / 0.75", "social_gan", "Mohamed et al. 2020, Table 1"),
    (
        "Trajectron++ (velocity leak fixed)",
        "0.27–0.32 / 0.50–0.55",
        "trajectron",
        "github.com/StanfordASL/Trajectron-plus-plus/issues/53; SocialVAE's table",
    ),
    ("PECNet", "0.29 / 0.48", "not checked", "Mangalam et al. 2020"),
    ("AgentFormer (leak fixed)", "0.23 / 0.39", "trajectron", "its README"),
    ("SocialVAE", "0.24 / 0.42", "trajectron", "Xu et al. 2022; its data.py, on these test files"),
    ("LED", "0.21 / 0.33", "not checked", "Mao et al. 2023, Table 4"),
)

Scores = dict[str, dict[str, float]]  # mode -> metric -> value


def score_modes(
    model,
    loader,
    denormalize: Callable,
    device="cpu",
    num_samples: int = NUM_SAMPLES,
    deterministic=False,
    modes: Sequence[str] = tuple(MODES),
) -> Scores:
    """``{mode: {ade, fde, min_ade_k, min_fde_k, windows}}`` of ``model`` on ``loader``'s windows,
    each of ``modes`` (default all four) on the same windows (metres when ``denormalize`` gives metres).

    ``deterministic``: the model's samples all equal its point forecast, so its minimum over them is
    the point error; they are not drawn (half the cost of a slow baseline)."""
    rows, _ = evaluate_presence_subsets(
        model,
        loader,
        [(mode, MODES[mode]) for mode in modes],
        denormalize,
        num_samples=0 if deterministic else num_samples,
        device=device,
    )
    missing = [mode for mode in modes if mode not in rows]
    if missing:
        raise ValueError(f"no test window can be scored in mode(s) {missing}: the trajectory is absent")
    if deterministic:
        for row in rows.values():
            row |= {"min_ade_k": row["ade"], "min_fde_k": row["fde"]}
    return {mode: {k: rows[mode][k] for k in (*METRICS, "windows")} for mode in modes}


def score_split(
    model,
    data: WindowDataset,
    split: str,
    batch_size: int,
    device="cpu",
    deterministic: bool = False,
    modes: Sequence[str] = tuple(MODES),
) -> Scores:
    """:func:`score_modes` of ``model`` on ``data``'s ``split`` windows, in the target's units; its
    samples drawn from a fixed seed, so scoring a model again gives the same numbers."""
    torch.manual_seed(0)
    loader = data.loader(split, batch_size)
    model = model.to(device).eval()
    denormalize = data.normalizer.denormalize_target
    return score_modes(model, loader, denormalize, device, deterministic=deterministic, modes=modes)


def constant_velocity_model(data: WindowDataset, heading_noise: float = 0.0) -> nn.Module:
    """The constant-velocity baseline on ``data``'s windows, in eval mode: with ``heading_noise`` (the
    std in radians) its samples turn the last velocity, in the target's units (the data's target std)."""
    std = data.normalizer.stats["target/std"].tolist()
    return build_model(
        {"name": "constant_velocity", "heading_noise": heading_noise, "target_scale": std},
        data.specs,
        data.config.history,
        data.config.horizon,
        len(std),
    ).eval()


def heading_noise_scores(
    data: WindowDataset, grid: Sequence[float], batch_size: int, device="cpu", split: str = "val"
) -> dict[float, float]:
    """``{std: all-modality minADE20}`` of constant velocity with each heading noise std of ``grid`` on
    ``data``'s ``split`` windows."""
    # Every mode scored, though only `all` is read: the samples' draws follow the modes scored.
    return {
        sigma: score_split(constant_velocity_model(data, sigma), data, split, batch_size, device)["all"][
            "min_ade_k"
        ]
        for sigma in grid
    }


def best_heading_noise(
    data: WindowDataset, grid: Sequence[float], batch_size: int, device="cpu"
) -> tuple[float, dict[float, float]]:
    """The std of ``grid`` whose constant velocity with heading noise has the lowest all-modality
    minADE20 on ``data``'s val split, and each std's val minADE20: picked on val, never on the test
    scene."""
    on_val = heading_noise_scores(data, grid, batch_size, device)
    return min(on_val, key=on_val.get), on_val


def average_over_scenes(
    per_scene: Mapping[str, Mapping[str, Scores]], scenes: Sequence[str] | None = None
) -> dict[str, Scores]:
    """``{model: {mode: {metric: mean over the scenes}}}`` from ``{scene: {model: scores}}``, over
    ``scenes`` (default all); only the models scored in each of them (the literature's average is
    over the five scenes, unweighted)."""
    scenes = list(per_scene if scenes is None else scenes)
    models = [m for m in per_scene[scenes[0]] if all(m in per_scene[s] for s in scenes)] if scenes else []
    return {
        model: {
            mode: {k: float(np.mean([per_scene[s][model][mode][k] for s in scenes])) for k in METRICS}
            for mode in MODES
        }
        for model in models
    }


def ade_fde_text(scores: Mapping[str, float], point: bool = False) -> str:
    """``"A/F"`` (minADE20/minFDE20, or ADE/FDE with ``point``) at two decimals."""
    a, f = ("ade", "fde") if point else ("min_ade_k", "min_fde_k")
    return f"{scores[a]:.2f}/{scores[f]:.2f}"


def summary_line(
    average: Mapping[str, Scores],
    paper: str,
    cv: str,
    baselines: Sequence[str],
    mode: str,
    spread: Mapping[str, Scores] | None = None,
    seeds: Sequence[int] = (),
) -> str:
    """The benchmark's last line: the paper model's minADE20/minFDE20 in three modes, constant velocity
    and the best baseline (lowest all-modality minADE20), then ``mode``, the run it came from (the
    benchmark names its mode and window set). With ``spread`` (``average``'s models' spread over
    ``seeds``, ``average`` their mean), the paper model's and the best baseline's numbers are followed
    by ``±`` their spread, and the paper model's first by the seeds."""
    best = min(baselines, key=lambda name: average[name]["all"]["min_ade_k"])

    def text(model: str, m: str) -> str:
        plain = ade_fde_text(average[model][m])
        return f"{plain} ±{ade_fde_text(spread[model][m])}" if spread else plain

    over = f" over seeds {','.join(map(str, seeds))}" if spread else ""
    return (
        f"summary: paper model minADE20/minFDE20 avg {text(paper, 'all')}{over} "
        f"(without scene {text(paper, 'without_scene')}, "
        f"without neighbours {text(paper, 'without_neighbours')}); "
        f"constant velocity {ade_fde_text(average[cv]['all'])}; "
        f"best baseline {best} {text(best, 'all')} ({mode})"
    )


def scores_table(rows: Mapping[str, Scores], deterministic: Sequence[str] = ()) -> str:
    """Markdown: one row per model, for each mode ``minADE20/minFDE20`` and ``ADE/FDE`` (metres)."""
    head = " | ".join(f"{mode} minADE20/minFDE20 | {mode} ADE/FDE" for mode in MODES)
    lines = [f"| model | {head} |", "|---" * (1 + 2 * len(MODES)) + "|"]
    for model, scores in rows.items():
        mark = " †" if model in deterministic else ""
        cells = " | ".join(
            f"{ade_fde_text(scores[m])}{mark} | {ade_fde_text(scores[m], point=True)}" for m in MODES
        )
        lines.append(f"| {model} | {cells} |")
    return "\n".join(lines)


def relative_rise(scores: Scores, mode: str) -> float:
    """How much ``mode``'s minADE20 exceeds the all-modality one (0.1 = 10% worse)."""
    return scores[mode]["min_ade_k"] / scores["all"]["min_ade_k"] - 1


def published_table() -> str:
    """Markdown: the published rows, each with the window set it is scored on and its source."""
    lines = ["| method | avg minADE20 / minFDE20 (m) | window set | source |", "|---|---|---|---|"]
    lines += [
        f"| {method} | {value} | {windows} | {source} |" for method, value, windows, source in PUBLISHED
    ]
    return "\n".join(lines)


def plot_forecasts_on_image(
    image: np.ndarray,
    to_pixel: Callable[[np.ndarray], np.ndarray],
    examples: Sequence[Mapping[str, np.ndarray]],
    path: Path,
    title: str,
) -> Path:
    """Draw each example's observed past, ground truth and samples (world metres, ``[*, 2]`` arrays
    under ``past``, ``future``, ``samples`` ``[K, T, 2]``) on ``image`` through ``to_pixel`` (world ->
    ``(row, col)``)."""
    fig, ax = plt.subplots(figsize=(image.shape[1] / 80, image.shape[0] / 80), dpi=100)
    ax.imshow(image)
    for i, example in enumerate(examples):
        for k, sample in enumerate(example["samples"]):
            rc = to_pixel(np.concatenate([example["past"][-1:], sample]))
            ax.plot(
                rc[:, 1],
                rc[:, 0],
                color="tab:orange",
                lw=0.8,
                alpha=0.6,
                label=f"{len(example['samples'])} samples" if i + k == 0 else None,
            )
        truth = to_pixel(np.concatenate([example["past"][-1:], example["future"]]))
        past = to_pixel(example["past"])
        ax.plot(truth[:, 1], truth[:, 0], color="lime", lw=2, label="ground truth" if i == 0 else None)
        ax.plot(past[:, 1], past[:, 0], color="white", lw=2, marker=".", label="observed" if i == 0 else None)
    ax.set_xlim(0, image.shape[1])
    ax.set_ylim(image.shape[0], 0)
    ax.set_axis_off()
    ax.set_title(title, fontsize=8)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def observed_positions(batch, stats: Mapping[str, torch.Tensor]) -> torch.Tensor:
    """``[B, H, 2]``: the observed ``trajectory`` modality's first two dims (the positions) in world
    units, denormalised with the data's statistics ``stats``."""
    trajectory = batch.get((keys.OBS, "trajectory"))[..., :2]
    return trajectory * stats["trajectory/std"][:2] + stats["trajectory/mean"][:2]


def draw_test_samples(
    model,
    data: WindowDataset,
    windows: int,
    scene: Scene,
    path: Path,
    title: str,
    num_samples: int = NUM_SAMPLES,
) -> Path:
    """``model``'s ``num_samples`` samples, the ground truth and the observed past of ``windows`` test
    windows spread evenly over the test split, drawn on the ``scene``'s reference frame through its
    world -> pixel map (:func:`plot_forecasts_on_image`); the samples drawn from a fixed seed, so a
    figure repeats."""
    ids = data.split_windows["test"]
    batch = data.batch(ids[torch.linspace(0, len(ids) - 1, windows).long()])
    torch.manual_seed(0)
    samples = model.eval().sample(batch.exclude(keys.TARGET), num_samples).get(keys.FORECAST_SAMPLES)
    stats = data.normalizer.stats
    examples = world_examples(
        batch, samples.detach(), lambda b: observed_positions(b, stats), data.normalizer.denormalize_target
    )
    return plot_forecasts_on_image(scene.image, scene.to_pixel, examples, path, title)


def world_examples(batch, samples: torch.Tensor, position_of: Callable, denormalize: Callable) -> list[dict]:
    """Per window of ``batch``: observed past, ground truth and samples in world metres.

    ``position_of(batch)`` gives the ``[B, H, 2]`` absolute observed positions; the target and the
    samples ``[B, K, T, 2]`` are normalised displacements from the last observed one."""
    past = position_of(batch)
    origin = past[:, -1:, :]
    future = denormalize(batch.get(keys.TARGET)) + origin
    drawn = denormalize(samples) + origin[:, None]
    return [
        {"past": past[i].numpy(), "future": future[i].numpy(), "samples": drawn[i].numpy()}
        for i in range(past.shape[0])
    ]
