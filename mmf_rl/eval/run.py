"""`mmf-rl eval checkpoint=RUN_DIR [overrides]`: score a trained forecaster on every presence subset.

    mmf-rl eval checkpoint=runs/forecaster                  # the run's last checkpoint, its test split
    mmf-rl eval checkpoint=runs/forecaster data_root=/data/copy num_samples=50
    mmf-rl eval checkpoint=runs/forecaster eval_latent=predictive   # no retraining

For each subset (all modalities, each leave-one-out, each single modality) it reports MSE
(normalised and in units), ADE/FDE of the point forecast, minMSE/minADE/minFDE over K prior
samples, NLL, the coverage of the forecast's central 50% and 90% intervals, and the relative
degradation against all modalities; the constant-velocity baseline is a reference row. The rows
are paired: all are scored on the windows they share (see
:func:`~mmf_rl.eval.metrics.evaluate_presence_subsets`), with the window counts in the table.
Writes ``results.json``, ``results.md`` and the plots into ``out_dir`` (default ``RUN_DIR/eval``).
An ``out_dir`` outside the run directory needs ``allow_outside_run_dir=true``: a config copied
from elsewhere cannot make an evaluation write over unrelated files by accident.

``eval_latent`` / ``predictive_samples`` (``null``: as trained) score the checkpoint with another
eval-mode latent of its model (see :class:`~mmf_rl.models.ForecasterConfig`), without retraining:
e.g. ``eval_latent=predictive`` folds the spread of the prior's samples into the forecast's scale.
The values used are recorded in ``results.json`` and the header of ``results.md``.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError, load_checkpoint, load_model_state
from mmf_rl.configuration import ConfigError, parse_config_command
from mmf_rl.datasets import DataConfig, WindowDataset, apply_presence_subset, presence_subsets
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.devices import resolve_device
from mmf_rl.eval.metrics import evaluate_presence_subsets, scorable_windows
from mmf_rl.eval.report import (
    markdown_table,
    plot_error_per_subset,
    plot_forecasts,
    plot_latent_tsne,
    write_json,
    write_text,
)
from mmf_rl.models import MODELS, model_from_saved_config

EXAMPLES = [
    "mmf-rl eval checkpoint=runs/forecaster                  # the run's last checkpoint, its test split",
    "mmf-rl eval checkpoint=runs/forecaster split=val num_samples=50 plots=false",
    "mmf-rl eval checkpoint=runs/forecaster eval_latent=predictive predictive_samples=32",
]
LATENT_SETTINGS = ("eval_latent", "predictive_samples")  # model settings an eval may override
BASELINE_KEYS = {"cv_mse": "mse", "cv_mse_units": "mse_units", "cv_ade": "ade", "cv_fde": "fde"}


def checkpoint_location(path: Path) -> Path:
    """A run directory, its ``checkpoints/`` or a single checkpoint directory."""
    return path / "checkpoints" if (path / "checkpoints").is_dir() else path


def check_modalities_match(model_specs, data_specs, checkpoint_path: Path, data_root) -> None:
    def describe(specs):
        return {s.name: (s.kind, tuple(s.shape)) for s in specs}

    model_side, data_side = describe(model_specs), describe(data_specs)
    if model_side != data_side:
        raise CheckpointError(
            f"the checkpoint {checkpoint_path} was trained on modalities {model_side} but the data "
            f"at {data_root} gives {data_side}; evaluate on a dataset with the same features"
        )


def output_directory(cfg, run_dir: Path) -> Path:
    """``out_dir`` resolved; outside ``run_dir`` only when ``allow_outside_run_dir`` says so."""
    run_dir = run_dir.resolve()
    if cfg.out_dir is None:
        return run_dir / "eval"
    out_dir = Path(cfg.out_dir).resolve()
    if not out_dir.is_relative_to(run_dir) and not cfg.allow_outside_run_dir:
        raise ConfigError(
            f"out_dir={cfg.out_dir} resolves to {out_dir}, outside the run directory {run_dir}; "
            "pass allow_outside_run_dir=true to write there, or choose an out_dir inside the run"
        )
    return out_dir


def model_config_for_eval(saved: dict, overrides: dict, checkpoint_path: Path) -> dict:
    """The checkpoint's saved model config with the eval's latent ``overrides``, checked by the
    model's config class (a bad value or a model without the setting is a clear error)."""
    if not overrides:
        return saved
    name = saved.get("name", "forecaster")
    entry = MODELS.get(name)
    settings = {f.name for f in dataclasses.fields(entry.config_cls)} if entry else set()
    given = ", ".join(f"{key}={value}" for key, value in overrides.items())
    unknown = [key for key in overrides if key not in settings]
    if unknown:
        raise ConfigError(
            f"{given}: the {name!r} model of {checkpoint_path} has no setting {', '.join(unknown)}; "
            "remove it (eval_latent and predictive_samples are settings of model=forecaster)"
        )
    config = {**saved, **overrides}
    try:
        entry.config_cls.from_dict({key: value for key, value in config.items() if key != "name"})
    except ValueError as err:
        raise ConfigError(f"{given} for the {name!r} model of {checkpoint_path}: {err}") from None
    return config


def latent_used(model, overrides: dict) -> dict:
    """How the forecasts were decoded, for the results: the model's ``eval_latent`` (``None`` for a
    model without latent), ``predictive_samples`` when it applies, and the eval's overrides."""
    eval_latent = getattr(model.config, "eval_latent", None)
    samples = model.config.predictive_samples if eval_latent == "predictive" else None
    return {"eval_latent": eval_latent, "predictive_samples": samples, "latent_overrides": overrides}


def latent_header(used: dict) -> str:
    """The results.md line saying how the forecasts were decoded ("" for a model without latent)."""
    if used["eval_latent"] is None:
        return ""
    line = f"Forecast latent: eval_latent={used['eval_latent']}"
    if used["predictive_samples"] is not None:
        line += f", predictive_samples={used['predictive_samples']}"
    overrides = used["latent_overrides"]
    origin = ", ".join(f"{k}={v}" for k, v in overrides.items()) if overrides else None
    return f"{line} ({f'set by this eval: {origin}' if origin else 'as trained'})\n\n"


def run_evaluation(cfg) -> dict:
    device = resolve_device(cfg.device)
    checkpoint = load_checkpoint(checkpoint_location(Path(cfg.checkpoint)), with_trainer_state=False)
    # Checked before the slow part: a refused out_dir fails in a second, not after the scoring.
    out_dir = output_directory(cfg, checkpoint.path.parent.parent)
    train_cfg = checkpoint.meta.get("config")
    if not train_cfg or "model_config" not in checkpoint.meta:
        raise CheckpointError(
            f"{checkpoint.path}/meta.json lacks the run config; it was not written by `mmf-rl train`"
        )
    data_dict = dict(train_cfg["data"])
    if cfg.data_root is not None:
        data_dict["root"] = str(cfg.data_root)
    data = WindowDataset(DataConfig.from_dict(data_dict))
    # Normalise with the statistics the model was trained with, whatever data it is scored on.
    data.normalizer = Normalizer(checkpoint.tensors)
    overrides = {name: cfg[name] for name in LATENT_SETTINGS if cfg[name] is not None}
    # Applied to the saved config before building: the model's fixed draws follow predictive_samples.
    model = model_from_saved_config(
        model_config_for_eval(checkpoint.meta["model_config"], overrides, checkpoint.path)
    )
    check_modalities_match(model.modalities, data.specs, checkpoint.path, data.config.root)
    load_model_state(model, checkpoint)
    model.to(device).eval()

    if len(data.split_windows[cfg.split]) == 0:
        raise ValueError(
            f"the {cfg.split!r} split of {data.config.root} has no window; evaluate another split "
            "(split=val|train) or record more episodes"
        )
    loader = data.loader(cfg.split, cfg.batch_size)
    denormalize = data.normalizer.denormalize_target
    with_baseline = data.config.include_target_past
    torch.manual_seed(cfg.seed)  # best-of-K draws are repeatable

    subsets = list(presence_subsets([s.name for s in data.specs]))
    results, baseline = evaluate_presence_subsets(
        model,
        loader,
        subsets,
        lambda t: denormalize(t.cpu()).to(t),
        num_samples=cfg.num_samples,
        with_baseline=with_baseline,
        device=device,
    )
    skipped = [name for name, _ in subsets if name not in results]

    out_dir.mkdir(parents=True, exist_ok=True)
    units = f"units of {data.config.target.feature}"
    notes = (
        [f"not scored (no {cfg.split} window has any of their modalities): {', '.join(skipped)}"]
        if skipped
        else []
    )
    summary = {
        "checkpoint": str(checkpoint.path),
        "step": checkpoint.step,
        "split": cfg.split,
        "data_root": str(data.config.root),
        "num_samples": cfg.num_samples,
        **latent_used(model, overrides),
        "subsets": results,
        "constant_velocity": baseline,
    }
    plots = []
    if cfg.plots:
        plots, plot_notes = make_plots(
            model, data, loader, denormalize, cfg, out_dir, units, results, baseline
        )
        notes += plot_notes
    summary["notes"] = notes
    write_json(out_dir / "results.json", summary)
    table = markdown_table(results, baseline, units, cfg.num_samples)
    table += "".join(f"\nNote: {note}\n" for note in notes)
    write_text(
        out_dir / "results.md",
        f"# {checkpoint.path} on {data.config.root} ({cfg.split} split)\n\n{latent_header(summary)}{table}",
    )
    summary["table"], summary["plots"] = table, [str(p) for p in plots]
    return summary


@torch.no_grad()
def make_plots(
    model, data, loader, denormalize, cfg, out_dir: Path, units: str, results: dict, baseline: dict | None
) -> tuple[list[Path], list[str]]:
    """Forecasts vs truth on a few test windows, error per subset, t-SNE of the test-time latents.

    Returns the plots written and notes on those left out (and why)."""
    paths = [out_dir / "error_per_subset.png", out_dir / "forecasts.png", out_dir / "latent_tsne.png"]
    plot_error_per_subset(results, baseline, paths[0])

    device = next(model.parameters()).device
    subsets = [
        (name, subset) for name, subset in presence_subsets([s.name for s in data.specs]) if name in results
    ]
    # Paired like the table: the first batch's windows that every subset can score, the same in every row.
    shared = None
    for candidate in loader:
        rows = torch.stack([scorable_windows(candidate, subset) for _, subset in subsets]).all(0)
        if rows.any():
            shared = candidate[rows]
            break
    picks = torch.linspace(0, shared.shape[0] - 1, min(cfg.plot_windows, shared.shape[0])).long()
    examples, latents = {}, {}
    for name, subset in subsets:
        batch = apply_presence_subset(shared[picks], subset)
        inputs = batch.exclude(keys.TARGET).to(device)
        out = model(inputs.clone())
        past = batch.get(keys.TARGET_PAST, None)
        examples[name] = {
            "target": denormalize(batch.get(keys.TARGET)),
            "mean": denormalize(out.get(keys.FORECAST_LOC).cpu()),
            "past": denormalize(past) if past is not None else None,
            "samples": denormalize(
                model.sample(inputs.clone(), num_samples=min(cfg.num_samples, 10))
                .get(keys.FORECAST_SAMPLES)
                .cpu()
            )
            if cfg.num_samples
            else None,
        }
        # The latents the test-time forecasts are decoded from (no target: not the posterior).
        latent = model(
            apply_presence_subset(shared[: cfg.tsne_windows], subset).exclude(keys.TARGET).to(device)
        ).get(keys.LATENT, None)
        if latent is not None:
            latents[name] = latent.cpu()
    plot_forecasts(examples, paths[1], units)
    if not latents:
        return paths[:2], ["no latent t-SNE: the model has no latent (a deterministic baseline)"]
    if float(torch.cat(list(latents.values())).std(0).max()) == 0:
        note = (
            "no latent t-SNE: every test-time forecast is decoded from the same latent (under the standard "
            "prior its mean, z = 0); train with model.prior=learned for latents that depend on the present "
            "modalities"
        )
        return paths[:2], [note]
    plot_latent_tsne(latents, paths[2], seed=cfg.seed)
    return paths, []


def main(argv: list[str]) -> int:
    command = parse_config_command(
        argv,
        "eval",
        "mmf-rl eval",
        "Score a trained forecaster on every presence subset "
        "of its dataset's test split: table, results.json and plots.",
        EXAMPLES,
    )
    try:
        cfg = command.compose("eval")
        if command.print_config:
            print(OmegaConf.to_yaml(cfg), end="")
            return 0
        if cfg.get("checkpoint") is None:
            raise ConfigError(
                "checkpoint=PATH is required (a run directory, its checkpoints/ or one checkpoint)"
            )
        summary = run_evaluation(cfg)
    except (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError) as err:
        if os.environ.get("MMF_RL_DEBUG"):
            raise
        print(
            f"mmf-rl eval: error: {err.args[0] if isinstance(err, KeyError) and err.args else err}",
            file=sys.stderr,
        )
        return 1
    print(f"{latent_header(summary)}{summary['table']}")
    for path in summary["plots"]:
        print(f"plot: {path}")
    return 0
