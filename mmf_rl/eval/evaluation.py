"""Scoring a trained forecaster on every presence subset: what ``mmf-rl eval`` runs, and
:func:`evaluate`, its Python entry point (``mmf_rl.evaluate``).

The composed eval config is typed once, by :class:`EvalConfig`, where the evaluation starts; the
command's documentation, :mod:`mmf_rl.eval.eval_command`, says what each setting does and what is
written where.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.configuration import ConfigError, config_or_overrides, to_container
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
from mmf_rl.objectives import output_distribution_of

LATENT_SETTINGS = ("eval_latent", "predictive_samples")  # model settings an eval may override
logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalConfig:
    """An evaluation's settings (``configs/eval.yaml``), typed once from the composed config
    (:meth:`from_config`). See :mod:`mmf_rl.eval.eval_command` for what each does."""

    checkpoint: str
    data_root: str | None
    out_dir: str | None
    allow_outside_run_dir: bool
    split: str
    num_samples: int
    eval_latent: str | None
    predictive_samples: int | None
    batch_size: int
    device: str
    seed: int
    plots: bool
    plot_windows: int
    tsne_windows: int

    @classmethod
    def from_config(cls, cfg: DictConfig) -> EvalConfig:
        """Type a composed eval config; ``checkpoint`` is required."""
        if cfg.get("checkpoint") is None:
            raise ConfigError(f"checkpoint=PATH is required: {TRAINED_MODEL_KINDS}")
        settings = to_container(cfg)
        return cls(**{field.name: settings[field.name] for field in fields(cls)})


def check_modalities_match(model_specs, data_specs, source_path: Path, data_root) -> None:
    def describe(specs):
        return {s.name: (s.kind, tuple(s.shape)) for s in specs}

    model_side, data_side = describe(model_specs), describe(data_specs)
    if model_side != data_side:
        raise CheckpointError(
            f"the model {source_path} was trained on modalities {model_side} but the data "
            f"at {data_root} gives {data_side}; evaluate on a dataset with the same features"
        )


def output_directory(eval_cfg: EvalConfig, source: TrainedModelSource) -> Path:
    """``out_dir`` resolved (default: ``eval/`` in the run directory, or in the save_pretrained
    directory); outside that directory only when ``allow_outside_run_dir`` says so."""
    from huggingface_hub.constants import HF_HUB_CACHE

    home = (source.path if source.kind == "save_pretrained" else source.path.parent.parent).resolve()
    if eval_cfg.out_dir is None:
        if home.is_relative_to(Path(HF_HUB_CACHE).resolve()):
            raise ConfigError(
                f"{source.path} is in the Hugging Face cache ({HF_HUB_CACHE}); pass out_dir=DIR "
                "allow_outside_run_dir=true to write the evaluation elsewhere"
            )
        return home / "eval"
    out_dir = Path(eval_cfg.out_dir).resolve()
    if not out_dir.is_relative_to(home) and not eval_cfg.allow_outside_run_dir:
        what = "save_pretrained directory" if source.kind == "save_pretrained" else "run directory"
        raise ConfigError(
            f"out_dir={eval_cfg.out_dir} resolves to {out_dir}, outside the {what} {home}; "
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


def distribution_header(summary: dict) -> str:
    """The results.md line naming the forecast's output family when it is not the Gaussian (its NLL,
    intervals and CRPS are the family's)."""
    family = summary.get("output_distribution", "normal")
    if family == "normal":
        return ""
    return f"Forecast distribution: {family} (NLL, interval coverage and width, CRPS under it)\n\n"


def headers(summary: dict) -> str:
    """The lines above the results table: the forecast's distribution (when not the Gaussian), how the
    forecasts were decoded, how their scale was calibrated."""
    return (
        distribution_header(summary)
        + latent_header(summary)
        + calibration_header(summary["scale_calibration"])
    )


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


def load_for_evaluation(eval_cfg: EvalConfig, source: TrainedModelSource, overrides: dict, device):
    """The trained model on ``device`` in eval mode and its data (:func:`open_model_and_data`);
    refuses a split with no window."""
    model, data = open_model_and_data(source, eval_cfg.data_root, overrides)
    model.to(device).eval()
    if len(data.split_windows[eval_cfg.split]) == 0:
        raise ValueError(
            f"the {eval_cfg.split!r} split of {data.config.root} has no window; evaluate another split "
            "(split=val|train) or record more episodes"
        )
    return model, data


def check_eval_settings(eval_cfg: EvalConfig) -> None:
    """The eval settings that would otherwise fail deep inside torch or matplotlib, or as a bare
    KeyError, after the model and data are loaded."""
    if eval_cfg.split not in SPLIT_NAMES:
        raise ConfigError(f"split={eval_cfg.split!r}: expected one of {', '.join(SPLIT_NAMES)}")
    if eval_cfg.num_samples < 0:
        raise ConfigError(
            f"num_samples={eval_cfg.num_samples}: must be >= 0 (0: point-forecast metrics only)"
        )
    for name in ("plot_windows", "tsne_windows"):
        if eval_cfg.plots and getattr(eval_cfg, name) < 1:
            raise ConfigError(f"{name}={getattr(eval_cfg, name)}: must be >= 1, or pass plots=false")


def evaluate(config: DictConfig | None = None, *, overrides: Sequence[str] = ()) -> dict:
    """Score a trained forecaster on every presence subset of its data as ``mmf-rl eval`` does, and
    write ``results.json``, ``results.md`` and the plots into the evaluation's ``out_dir``.

    Args:
        config (DictConfig, optional): a composed eval config, as ``mmf-rl eval --cfg`` prints it
            (:func:`~mmf_rl.configuration.compose_config`, edited as you like). ``None``: compose
            ``configs/eval.yaml`` with ``overrides``. ``checkpoint`` is required.

    Keyword Args:
        overrides (Sequence[str], optional): Hydra overrides, as on the command line (``key=value``);
            only without ``config``.

    Returns:
        The summary written to ``results.json`` (``subsets``: the metrics of each presence subset,
        ``constant_velocity``: the reference row, ``notes``, ...), with the markdown ``table`` and
        the ``plots`` written.

    Raises:
        ValueError: both ``config`` and ``overrides`` given.

    Examples:
        A run trained for 2 steps on a tiny recording (as in :func:`mmf_rl.train`'s example), scored:

        >>> import tempfile
        >>> from pathlib import Path
        >>> import mmf_rl
        >>> from mmf_rl.record import RecordConfig, record
        >>> tmp = Path(tempfile.mkdtemp())
        >>> root = record(RecordConfig(out=tmp / "push", episodes=6, steps=40, image_size=32))
        >>> run_dir = mmf_rl.train(overrides=[
        ...     f"data.root={root}", f"run_dir={tmp / 'run'}", "data.image_size=[32,32]",
        ...     "data.history=4", "data.horizon=3", "model.d_model=16", "model.num_heads=2",
        ...     "trainer.total_steps=2", "trainer.batch_size=8", "trainer.progress_bar=false",
        ...     "logger=csv", "num_workers=0"])
        >>> summary = mmf_rl.evaluate(overrides=[f"checkpoint={run_dir}", "plots=false"])
        >>> sorted(summary["subsets"])[:3]  # every presence subset
        ['all', 'only_force', 'only_image']
        >>> summary["subsets"]["all"]["mse"] > 0
        True
    """
    eval_cfg = EvalConfig.from_config(config_or_overrides("eval", config, overrides))
    check_eval_settings(eval_cfg)
    device = resolve_device(eval_cfg.device)
    source = locate_trained_model(eval_cfg.checkpoint)
    # Checked before the slow part: a refused out_dir fails in a second, not after the scoring.
    out_dir = output_directory(eval_cfg, source)
    # the model settings this evaluation changes
    latent = {name: value for name in LATENT_SETTINGS if (value := getattr(eval_cfg, name)) is not None}
    model, data = load_for_evaluation(eval_cfg, source, latent, device)
    unfit = unfit_for_latent(model)
    loader = data.loader(eval_cfg.split, eval_cfg.batch_size, shuffle=False)  # every window once, train too
    denormalize = data.normalizer.denormalize_target
    torch.manual_seed(eval_cfg.seed)  # best-of-K draws are repeatable

    subsets = list(presence_subsets([s.name for s in data.specs]))
    results, baseline = evaluate_presence_subsets(
        model,
        loader,
        subsets,
        lambda t: denormalize(t.cpu()).to(t),
        num_samples=eval_cfg.num_samples,
        with_baseline=data.config.include_target_past,
        device=device,
    )
    skipped = [name for name, _ in subsets if name not in results]

    out_dir.mkdir(parents=True, exist_ok=True)
    notes = evaluation_notes(
        eval_cfg.split, skipped, unfit, source, data.config.target.anchored, results, baseline
    )
    summary = {
        "checkpoint": str(source.path),
        "model_format": source.kind,
        "step": source.step,
        "split": eval_cfg.split,
        "data_root": str(data.config.root),
        "num_samples": eval_cfg.num_samples,
        **latent_used(model, latent),
        "output_distribution": output_distribution_of(model).describe(),
        "scale_calibration": calibration_in_use(model),
        "subsets": results,
        "constant_velocity": baseline,
    }
    plots = []
    if eval_cfg.plots:
        plots, plot_notes = make_plots(model, data, loader, denormalize, eval_cfg, out_dir, results, baseline)
        notes += plot_notes
    summary["notes"] = notes
    write_results(out_dir, summary, source, data, eval_cfg)
    summary["plots"] = [str(p) for p in plots]
    return summary


def target_units(data: WindowDataset) -> str:
    """What the table's and plots' unnormalised errors are measured in."""
    return f"units of {data.config.target.feature}"


def write_results(
    out_dir: Path, summary: dict, source: TrainedModelSource, data, eval_cfg: EvalConfig
) -> None:
    """``results.json`` (the summary) and ``results.md`` (headers, table, notes); the table goes
    into ``summary["table"]``."""
    write_json(out_dir / "results.json", summary)
    results, baseline = summary["subsets"], summary["constant_velocity"]
    table = markdown_table(results, baseline, target_units(data), eval_cfg.num_samples)
    table += "".join(f"\nNote: {note}\n" for note in summary["notes"])
    write_text(
        out_dir / "results.md",
        f"# {source.path} on {data.config.root} ({eval_cfg.split} split)\n\n{headers(summary)}{table}",
    )
    summary["table"] = table


@torch.no_grad()
def make_plots(
    model,
    data,
    loader,
    denormalize,
    eval_cfg: EvalConfig,
    out_dir: Path,
    results: dict,
    baseline: dict | None,
) -> tuple[list[Path], list[str]]:
    """Forecasts vs truth on a few test windows, error per subset, t-SNE of the test-time latents.

    Returns the plots written and notes on those left out (and why)."""
    paths = [out_dir / "error_per_subset.png", out_dir / "forecasts.png", out_dir / "latent_tsne.png"]
    plot_error_per_subset(results, baseline, paths[0])
    subsets = [
        (name, subset) for name, subset in presence_subsets([s.name for s in data.specs]) if name in results
    ]
    shared = first_shared_windows(loader, subsets)
    picks = torch.linspace(0, shared.shape[0] - 1, min(eval_cfg.plot_windows, shared.shape[0])).long()
    examples, latents = {}, {}
    for name, subset in subsets:
        examples[name] = forecast_example(
            model, apply_presence_subset(shared[picks], subset), denormalize, min(eval_cfg.num_samples, 10)
        )
        latent = test_time_latent(model, apply_presence_subset(shared[: eval_cfg.tsne_windows], subset))
        if latent is not None:
            latents[name] = latent
    plot_forecasts(examples, paths[1], target_units(data))
    note = latent_plot_refused(latents)
    if note is not None:
        return paths[:2], [note]
    plot_latent_tsne(latents, paths[2], seed=eval_cfg.seed)
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
