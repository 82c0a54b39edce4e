"""`mmf-rl eval checkpoint=DIR [overrides]`: score a trained forecaster on every presence subset.

    mmf-rl eval checkpoint=runs/forecaster                  # the run's last checkpoint, its test split
    mmf-rl eval checkpoint=runs/forecaster data_root=/data/copy num_samples=50
    mmf-rl eval checkpoint=runs/forecaster eval_latent=predictive   # no retraining
    mmf-rl eval checkpoint=exports/g1 data_root=/data/g1    # a save_pretrained directory (or hub download)

``checkpoint`` is a training run directory, its ``checkpoints/``, one checkpoint, or a directory
written by ``save_pretrained`` (``config.json``, ``model.safetensors``, ``normalization.safetensors``,
``data_config.json``: what ``mmf-rl train`` leaves in ``RUN_DIR/model``, ``model.save_pretrained(dir)``
writes, or ``hf download USER/MODEL --local-dir DIR`` fetches). The model is scored on the data
its data config names, with its normalisation statistics; ``data_root`` says where that dataset
is on this machine when it is elsewhere (a saved root that does not exist here is an error
naming it).

For each subset (all modalities, each leave-one-out, each single modality) it reports MSE
(normalised and in units), ADE/FDE of the point forecast, minMSE/minADE/minFDE over K prior
samples, NLL, the coverage of the forecast's central 50% and 90% intervals, and the relative
degradation against all modalities; the constant-velocity baseline is a reference row. The rows
are paired: all are scored on the windows they share (see
:func:`~mmf_rl.eval.metrics.evaluate_presence_subsets`), with the window counts in the table.
Writes ``results.json``, ``results.md`` and the plots into ``out_dir``: by default ``RUN_DIR/eval``
for a run or its checkpoints, ``DIR/eval`` for a save_pretrained directory (the directory stands
for the run: a copy of the model carries its evaluations). An ``out_dir`` outside that directory
needs ``allow_outside_run_dir=true``: a config copied from elsewhere cannot make an evaluation
write over unrelated files by accident. A save_pretrained directory inside the Hugging Face cache
(``from_pretrained``'s or ``snapshot_download``'s copy) needs an ``out_dir`` elsewhere: the cache
is not a place for results. ``results.json`` names the ``checkpoint`` scored and its training
``step``; a save_pretrained directory records no step (``step: null``, and a note says so).

``eval_latent`` / ``predictive_samples`` (``null``: as trained) score the model with another
eval-mode latent (see :class:`~mmf_rl.models.ForecasterConfig`), without retraining: e.g.
``eval_latent=predictive`` folds the spread of the prior's samples into the forecast's scale.
They are applied to the saved model config before the model is built, for a checkpoint and a
save_pretrained directory alike (``load_trained_model(..., config_overrides=...)``). The values
used are recorded in ``results.json`` and the header of ``results.md``.

A model whose scale was recalibrated per presence pattern (``mmf-rl calibrate``) is scored with
its factors, as stored; ``results.json`` (``scale_calibration``) and the header of ``results.md``
say so and on which split they were fitted.
"""

from __future__ import annotations

import logging
from pathlib import Path

import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.configuration import ConfigError, parse_config_command, report_command_error
from mmf_rl.datasets import DataConfig, WindowDataset, apply_presence_subset, presence_subsets
from mmf_rl.datasets.config import SPLIT_NAMES
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.devices import resolve_device
from mmf_rl.eval.metrics import evaluate_presence_subsets, scorable_windows
from mmf_rl.eval.report import (
    constant_velocity_warning,
    markdown_table,
    plot_error_per_subset,
    plot_forecasts,
    plot_latent_tsne,
    write_json,
    write_text,
)
from mmf_rl.eval.scale_fit import calibration_header, calibration_in_use, unfit_for_latent
from mmf_rl.models import TrainedModelSource, load_trained_model, locate_trained_model
from mmf_rl.models.loading import TRAINED_MODEL_KINDS

EXAMPLES = [
    "mmf-rl eval checkpoint=runs/forecaster                  # the run's last checkpoint, its test split",
    "mmf-rl eval checkpoint=runs/forecaster split=val num_samples=50 plots=false",
    "mmf-rl eval checkpoint=runs/forecaster eval_latent=predictive predictive_samples=32",
    "mmf-rl eval checkpoint=exports/g1 data_root=/data/g1     # save_pretrained dir -> exports/g1/eval",
]
LATENT_SETTINGS = ("eval_latent", "predictive_samples")  # model settings an eval may override
logger = logging.getLogger(__name__)


def check_modalities_match(model_specs, data_specs, source_path: Path, data_root) -> None:
    def describe(specs):
        return {s.name: (s.kind, tuple(s.shape)) for s in specs}

    model_side, data_side = describe(model_specs), describe(data_specs)
    if model_side != data_side:
        raise CheckpointError(
            f"the model {source_path} was trained on modalities {model_side} but the data "
            f"at {data_root} gives {data_side}; evaluate on a dataset with the same features"
        )


def output_directory(cfg, source: TrainedModelSource) -> Path:
    """``out_dir`` resolved (default: ``eval/`` in the run directory, or in the save_pretrained
    directory); outside that directory only when ``allow_outside_run_dir`` says so."""
    from huggingface_hub.constants import HF_HUB_CACHE

    home = (source.path if source.kind == "save_pretrained" else source.path.parent.parent).resolve()
    if cfg.out_dir is None:
        if home.is_relative_to(Path(HF_HUB_CACHE).resolve()):
            raise ConfigError(
                f"{source.path} is in the Hugging Face cache ({HF_HUB_CACHE}); pass out_dir=DIR "
                "allow_outside_run_dir=true to write the evaluation elsewhere"
            )
        return home / "eval"
    out_dir = Path(cfg.out_dir).resolve()
    if not out_dir.is_relative_to(home) and not cfg.allow_outside_run_dir:
        what = "save_pretrained directory" if source.kind == "save_pretrained" else "run directory"
        raise ConfigError(
            f"out_dir={cfg.out_dir} resolves to {out_dir}, outside the {what} {home}; "
            f"pass allow_outside_run_dir=true to write there, or choose an out_dir inside {home}"
        )
    return out_dir


def data_config_for_eval(saved: dict, data_root, source: TrainedModelSource) -> DataConfig:
    """The data config the model was trained with, on ``data_root`` when given. A saved root that
    does not exist here (a model trained on another machine) is an error naming ``data_root=``."""
    data = dict(saved)
    if data_root is not None:
        data["root"] = str(data_root)
    elif data.get("root") is not None and not Path(data["root"]).exists():
        raise ConfigError(
            f"the data config saved with {source.path} reads the dataset at {data['root']}, which does not "
            f"exist on this machine (from {Path.cwd()}); pass data_root=/path/to/the/dataset (a copy with "
            f"the same features: {', '.join(sorted(data.get('modalities', {})))})"
        )
    # Losing a modality on most frames stops training, not scoring: an evaluation scores what the data
    # holds (the missing-file warning and the table's `available` column show what was lost).
    data["modalities"] = {
        name: {**({"feature": m} if isinstance(m, str) else dict(m)), "allow_absent": True}
        for name, m in data.get("modalities", {}).items()
    }
    return DataConfig.from_dict(data)


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


def headers(summary: dict) -> str:
    """The lines above the results table: how the forecasts were decoded, how their scale was
    calibrated."""
    return latent_header(summary) + calibration_header(summary["scale_calibration"])


def evaluation_notes(
    split: str, skipped: list[str], unfit: str | None, source, relative: bool, results: dict, baseline
) -> list[str]:
    """The notes under the results table; a model losing to constant velocity is also a logged warning."""
    notes = (
        [f"not scored (no {split} window has any of their modalities): {', '.join(skipped)}"]
        if skipped
        else []
    )
    if unfit is not None:
        notes.append(unfit)
    losing = constant_velocity_warning(results, baseline, relative)
    if losing is not None:
        logger.warning(losing)
        notes.append(losing)
    if source.step is None:
        notes.append(
            f"training step unknown: {source.path} is a save_pretrained directory, which records none"
        )
    return notes


def open_model_and_data(source: TrainedModelSource, data_root, overrides: dict | None = None):
    """The trained model and the data of its data config (on ``data_root`` when given), normalised
    with the model's training statistics; refuses data whose modalities differ from the model's."""
    # Applied to the saved config before building: the model's fixed draws follow predictive_samples.
    model, stats, data_config = load_trained_model(source.path, config_overrides=overrides)
    data = WindowDataset(data_config_for_eval(data_config, data_root, source))
    # Normalise with the statistics the model was trained with, whatever data it is scored on.
    data.normalizer = Normalizer(stats)
    check_modalities_match(model.modalities, data.specs, source.path, data.config.root)
    return model, data


def load_for_evaluation(cfg, source: TrainedModelSource, overrides: dict, device):
    """The trained model on ``device`` in eval mode and its data (:func:`open_model_and_data`);
    refuses a split with no window."""
    model, data = open_model_and_data(source, cfg.data_root, overrides)
    model.to(device).eval()
    if len(data.split_windows[cfg.split]) == 0:
        raise ValueError(
            f"the {cfg.split!r} split of {data.config.root} has no window; evaluate another split "
            "(split=val|train) or record more episodes"
        )
    return model, data


def check_eval_settings(cfg) -> None:
    """The eval settings that would otherwise fail deep inside torch or matplotlib, or as a bare
    KeyError, after the model and data are loaded."""
    if cfg.split not in SPLIT_NAMES:
        raise ConfigError(f"split={cfg.split!r}: expected one of {', '.join(SPLIT_NAMES)}")
    if cfg.num_samples < 0:
        raise ConfigError(f"num_samples={cfg.num_samples}: must be >= 0 (0: point-forecast metrics only)")
    for name in ("plot_windows", "tsne_windows"):
        if cfg.plots and cfg[name] < 1:
            raise ConfigError(f"{name}={cfg[name]}: must be >= 1, or pass plots=false")


def run_evaluation(cfg) -> dict:
    check_eval_settings(cfg)
    device = resolve_device(cfg.device)
    source = locate_trained_model(cfg.checkpoint)
    # Checked before the slow part: a refused out_dir fails in a second, not after the scoring.
    out_dir = output_directory(cfg, source)
    overrides = {name: cfg[name] for name in LATENT_SETTINGS if cfg[name] is not None}
    model, data = load_for_evaluation(cfg, source, overrides, device)
    unfit = unfit_for_latent(model)
    loader = data.loader(cfg.split, cfg.batch_size, shuffle=False)  # every window once, train too
    denormalize = data.normalizer.denormalize_target
    torch.manual_seed(cfg.seed)  # best-of-K draws are repeatable

    subsets = list(presence_subsets([s.name for s in data.specs]))
    results, baseline = evaluate_presence_subsets(
        model,
        loader,
        subsets,
        lambda t: denormalize(t.cpu()).to(t),
        num_samples=cfg.num_samples,
        with_baseline=data.config.include_target_past,
        device=device,
    )
    skipped = [name for name, _ in subsets if name not in results]

    out_dir.mkdir(parents=True, exist_ok=True)
    notes = evaluation_notes(
        cfg.split, skipped, unfit, source, data.config.target.anchored, results, baseline
    )
    summary = {
        "checkpoint": str(source.path),
        "model_format": source.kind,
        "step": source.step,
        "split": cfg.split,
        "data_root": str(data.config.root),
        "num_samples": cfg.num_samples,
        **latent_used(model, overrides),
        "scale_calibration": calibration_in_use(model),
        "subsets": results,
        "constant_velocity": baseline,
    }
    plots = []
    if cfg.plots:
        plots, plot_notes = make_plots(model, data, loader, denormalize, cfg, out_dir, results, baseline)
        notes += plot_notes
    summary["notes"] = notes
    write_results(out_dir, summary, source, data, cfg)
    summary["plots"] = [str(p) for p in plots]
    return summary


def target_units(data: WindowDataset) -> str:
    """What the table's and plots' unnormalised errors are measured in."""
    return f"units of {data.config.target.feature}"


def write_results(out_dir: Path, summary: dict, source: TrainedModelSource, data, cfg) -> None:
    """``results.json`` (the summary) and ``results.md`` (headers, table, notes); the table goes
    into ``summary["table"]``."""
    write_json(out_dir / "results.json", summary)
    results, baseline = summary["subsets"], summary["constant_velocity"]
    table = markdown_table(results, baseline, target_units(data), cfg.num_samples)
    table += "".join(f"\nNote: {note}\n" for note in summary["notes"])
    write_text(
        out_dir / "results.md",
        f"# {source.path} on {data.config.root} ({cfg.split} split)\n\n{headers(summary)}{table}",
    )
    summary["table"] = table


@torch.no_grad()
def make_plots(
    model, data, loader, denormalize, cfg, out_dir: Path, results: dict, baseline: dict | None
) -> tuple[list[Path], list[str]]:
    """Forecasts vs truth on a few test windows, error per subset, t-SNE of the test-time latents.

    Returns the plots written and notes on those left out (and why)."""
    paths = [out_dir / "error_per_subset.png", out_dir / "forecasts.png", out_dir / "latent_tsne.png"]
    plot_error_per_subset(results, baseline, paths[0])
    subsets = [
        (name, subset) for name, subset in presence_subsets([s.name for s in data.specs]) if name in results
    ]
    shared = first_shared_windows(loader, subsets)
    picks = torch.linspace(0, shared.shape[0] - 1, min(cfg.plot_windows, shared.shape[0])).long()
    examples, latents = {}, {}
    for name, subset in subsets:
        examples[name] = forecast_example(
            model, apply_presence_subset(shared[picks], subset), denormalize, min(cfg.num_samples, 10)
        )
        latent = test_time_latent(model, apply_presence_subset(shared[: cfg.tsne_windows], subset))
        if latent is not None:
            latents[name] = latent
    plot_forecasts(examples, paths[1], target_units(data))
    note = latent_plot_refused(latents)
    if note is not None:
        return paths[:2], [note]
    plot_latent_tsne(latents, paths[2], seed=cfg.seed)
    return paths, []


def first_shared_windows(loader, subsets: list[tuple[str, dict]]) -> TensorDictBase:
    """The first batch's windows that every subset can score: paired like the table, the same
    windows in every row."""
    for candidate in loader:
        rows = torch.stack([scorable_windows(candidate, subset) for _, subset in subsets]).all(0)
        if rows.any():
            return candidate[rows]
    raise ValueError("no window can be scored in every presence subset: nothing to plot (pass plots=false)")


def forecast_example(model, batch: TensorDictBase, denormalize, num_samples: int) -> dict:
    """One subset's windows for the forecast plot, in units: target, mean, past and up to
    ``num_samples`` samples (``None`` when there is no past or no sample)."""
    device = next(model.parameters()).device
    inputs = batch.exclude(keys.TARGET).to(device)
    out = model(inputs.clone())
    past = batch.get(keys.TARGET_PAST, None)
    samples = None
    if num_samples:
        samples = denormalize(
            model.sample(inputs.clone(), num_samples=num_samples).get(keys.FORECAST_SAMPLES).cpu()
        )
    return {
        "target": denormalize(batch.get(keys.TARGET)),
        "mean": denormalize(out.get(keys.FORECAST_LOC).cpu()),
        "past": denormalize(past) if past is not None else None,
        "samples": samples,
    }


def test_time_latent(model, batch: TensorDictBase) -> torch.Tensor | None:
    """The latents ``batch``'s test-time forecasts are decoded from (no target: not the posterior),
    on the CPU; ``None`` for a model without latent."""
    device = next(model.parameters()).device
    latent = model(batch.exclude(keys.TARGET).to(device)).get(keys.LATENT, None)
    return latent.cpu() if latent is not None else None


def latent_plot_refused(latents: dict[str, torch.Tensor]) -> str | None:
    """Why the latent t-SNE is not drawn (no latent, or one latent for every forecast); ``None``: draw it."""
    if not latents:
        return "no latent t-SNE: the model has no latent (a deterministic baseline)"
    if float(torch.cat(list(latents.values())).std(0).max()) == 0:
        return (
            "no latent t-SNE: every test-time forecast is decoded from the same latent (under the standard "
            "prior its mean, z = 0); train with model.prior=learned for latents that depend on the present "
            "modalities"
        )
    return None


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
            raise ConfigError(f"checkpoint=PATH is required: {TRAINED_MODEL_KINDS}")
        summary = run_evaluation(cfg)
    except (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError) as err:
        return report_command_error("mmf-rl eval", err)
    print(f"{headers(summary)}{summary['table']}")
    for path in summary["plots"]:
        print(f"plot: {path}")
    return 0
