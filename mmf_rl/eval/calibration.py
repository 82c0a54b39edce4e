"""Recalibrating a trained model's forecast scale per presence pattern on held-out windows: what
``mmf-rl calibrate`` runs, and :func:`calibrate`, its Python entry point.

The composed calibrate config is typed once, by :class:`CalibrateConfig`; the command's
documentation, :mod:`mmf_rl.eval.calibrate_command`, says what each setting does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import torch
from omegaconf import DictConfig

from mmf_rl.configuration import ConfigError, config_or_overrides, to_container
from mmf_rl.devices import resolve_device
from mmf_rl.eval.evaluation import open_model_and_data
from mmf_rl.eval.scale_fit import (
    CALIBRATION_METHODS,
    calibration_record,
    fit_scale_calibration,
    fit_table,
    save_calibration,
)
from mmf_rl.models import locate_trained_model
from mmf_rl.models.loading import TRAINED_MODEL_KINDS

FIT_SPLITS = ("val", "train")


@dataclass(frozen=True)
class CalibrateConfig:
    """A calibration's settings (``configs/calibrate.yaml``), typed once from the composed config
    (:meth:`from_config`). See :mod:`mmf_rl.eval.calibrate_command` for what each does."""

    checkpoint: str
    data_root: str | None
    split: str
    method: str
    per_step: bool
    min_windows: int
    batch_size: int
    device: str

    @classmethod
    def from_config(cls, cfg: DictConfig) -> CalibrateConfig:
        """Type a composed calibrate config; ``checkpoint`` is required."""
        if cfg.get("checkpoint") is None:
            raise ConfigError(f"checkpoint=PATH is required: {TRAINED_MODEL_KINDS}")
        settings = to_container(cfg)
        return cls(**{field.name: settings[field.name] for field in fields(cls)})


def calibrate(config: DictConfig | None = None, *, overrides: Sequence[str] = ()) -> dict:
    """Fit a trained model's forecast scale per presence pattern as ``mmf-rl calibrate`` does, and
    write the factors into its checkpoint or save_pretrained directory (and the run's other copy).

    Args:
        config: a composed calibrate config (:func:`~mmf_rl.configuration.compose_config`).
            ``None``: compose ``configs/calibrate.yaml`` with ``overrides``. ``checkpoint`` is required.
        overrides: Hydra overrides, as on the command line (``key=value``); only without ``config``.

    Returns:
        What the command prints: ``checkpoint``, ``split``, ``method``, ``per_step``, the ``fits``, their
        ``table``, ``notes`` on the patterns fitted together, and the paths ``written``.

    Examples:
        >>> from mmf_rl.eval.calibration import calibrate
        >>> fitted = calibrate(overrides=["checkpoint=runs/quick"])
        >>> print(fitted["table"])
    """
    calibrate_cfg = CalibrateConfig.from_config(config_or_overrides("calibrate", config, overrides))
    if calibrate_cfg.split not in FIT_SPLITS:
        raise ConfigError(
            f"split={calibrate_cfg.split!r}: the scale factors are fitted on {' or '.join(FIT_SPLITS)} "
            "(test must stay unseen to score them)"
        )
    if calibrate_cfg.method not in CALIBRATION_METHODS:
        raise ConfigError(f"method={calibrate_cfg.method!r}: choose among {', '.join(CALIBRATION_METHODS)}")
    device = resolve_device(calibrate_cfg.device)
    source = locate_trained_model(calibrate_cfg.checkpoint)
    model, data = open_model_and_data(source, calibrate_cfg.data_root)
    if len(data.split_windows[calibrate_cfg.split]) == 0:
        raise ValueError(
            f"the {calibrate_cfg.split!r} split of {data.config.root} has no window to fit the scale factors "
            "on; use split=train or record more episodes"
        )
    torch.manual_seed(0)  # eval_latent="sample" draws: a refit gives the same factors
    every_window = data.loader(
        calibrate_cfg.split, calibrate_cfg.batch_size, shuffle=False
    )  # train's loader would drop its tail
    fits = fit_scale_calibration(
        model, every_window, calibrate_cfg.min_windows, device, calibrate_cfg.method, calibrate_cfg.per_step
    )
    model.calibration = calibration_record(
        model,
        fits,
        calibrate_cfg.split,
        calibrate_cfg.min_windows,
        data.config.root,
        calibrate_cfg.method,
        calibrate_cfg.per_step,
    )
    written = save_calibration(model.cpu(), source)
    return {
        "checkpoint": str(source.path),
        "split": calibrate_cfg.split,
        "method": calibrate_cfg.method,
        "per_step": calibrate_cfg.per_step,
        "fits": fits,
        "table": fit_table(fits, calibrate_cfg.split),
        "notes": fallback_notes(fits, calibrate_cfg.min_windows, calibrate_cfg.split, calibrate_cfg.per_step),
        "written": [str(p) for p in written],
    }


def fallback_notes(fits, min_windows: int, split: str, per_step: bool = False) -> list[str]:
    """What the patterns with fewer than ``min_windows`` windows got instead of their own fit (with
    ``per_step``: instead of a factor per horizon step)."""
    notes = []
    pooled = [fit.pattern for fit in fits if fit.pooled]
    if pooled:
        at_every_step = ", one factor at every horizon step" if per_step else ""
        curve = " and its level curve" if any(fit.level_factors for fit in fits if fit.pooled) else ""
        notes.append(
            f"the pooled fit of every pattern{curve}{at_every_step} (fewer than min_windows={min_windows} "
            f"{split} windows): " + ", ".join(pooled)
        )
    kept = [fit.pattern for fit in fits if not fit.fitted and not fit.pooled]
    if kept:
        notes.append(
            f"kept at 1 (fewer than min_windows={min_windows} {split} windows, even all patterns "
            f"together): {', '.join(kept)}"
        )
    return notes
