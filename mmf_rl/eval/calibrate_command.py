"""`mmf-rl calibrate checkpoint=DIR [split=val] [method=coverage] [min_windows=32]`: recalibrate a
trained model's forecast scale per presence pattern, on held-out windows, and store the factors with
the model.

    mmf-rl calibrate checkpoint=runs/forecaster              # fit on its val split, write back
    mmf-rl eval checkpoint=runs/forecaster                   # then scores the calibrated model

``checkpoint`` is what ``mmf-rl eval`` takes (a run directory, its ``checkpoints/``, one checkpoint
or a ``save_pretrained`` directory), opened on its own data config and normalisation statistics
(``data_root`` when the dataset is elsewhere). The factors are fitted in closed form from the
uncalibrated scale (:mod:`mmf_rl.eval.scale_fit`; a refit replaces earlier factors), by
``method``: ``coverage`` (the default; the 90% intervals cover 90% of the split's values) or
``temperature`` (the NLL-optimal temperature, which heavy-tailed errors inflate), printed as
a table (pattern, windows, factor, 90% coverage on the split before -> after), and written
atomically into the checkpoint (re-saved at its step) or the ``save_pretrained`` directory, and
into the run's other copy of the same weights (``RUN_DIR/model`` or the last checkpoint). A later
``mmf-rl eval`` uses them without any flag, and its results say so.

``split=test`` is refused: a calibration fitted on the test futures would score itself.
"""

from __future__ import annotations

import torch
from omegaconf import OmegaConf

from mmf_rl.checkpoint import CheckpointError
from mmf_rl.configuration import ConfigError, parse_config_command, report_command_error
from mmf_rl.devices import resolve_device
from mmf_rl.eval.eval_command import open_model_and_data
from mmf_rl.eval.scale_fit import (
    CALIBRATION_METHODS,
    calibration_record,
    fit_scale_calibration,
    fit_table,
    save_calibration,
)
from mmf_rl.models import locate_trained_model
from mmf_rl.models.loading import TRAINED_MODEL_KINDS

EXAMPLES = [
    "mmf-rl calibrate checkpoint=runs/forecaster                 # its val split; then mmf-rl eval",
    "mmf-rl calibrate checkpoint=exports/g1 data_root=/data/g1 min_windows=64",
    "mmf-rl calibrate checkpoint=runs/forecaster method=temperature   # the NLL-optimal temperature",
]
FIT_SPLITS = ("val", "train")


def run_calibration(cfg) -> dict:
    if cfg.split not in FIT_SPLITS:
        raise ConfigError(
            f"split={cfg.split!r}: the scale factors are fitted on {' or '.join(FIT_SPLITS)} "
            "(test must stay unseen to score them)"
        )
    if cfg.method not in CALIBRATION_METHODS:
        raise ConfigError(f"method={cfg.method!r}: choose among {', '.join(CALIBRATION_METHODS)}")
    device = resolve_device(cfg.device)
    source = locate_trained_model(cfg.checkpoint)
    model, data = open_model_and_data(source, cfg.data_root)
    if len(data.split_windows[cfg.split]) == 0:
        raise ValueError(
            f"the {cfg.split!r} split of {data.config.root} has no window to fit the scale factors on; "
            "use split=train or record more episodes"
        )
    torch.manual_seed(0)  # eval_latent="sample" draws: a refit gives the same factors
    every_window = data.loader(cfg.split, cfg.batch_size, shuffle=False)  # train's loader would drop its tail
    fits = fit_scale_calibration(model, every_window, cfg.min_windows, device, cfg.method)
    model.calibration = calibration_record(
        model, fits, cfg.split, cfg.min_windows, data.config.root, cfg.method
    )
    written = save_calibration(model.cpu(), source)
    return {
        "checkpoint": str(source.path),
        "split": cfg.split,
        "method": cfg.method,
        "fits": fits,
        "table": fit_table(fits, cfg.split),
        "notes": fallback_notes(fits, cfg.min_windows, cfg.split),
        "written": [str(p) for p in written],
    }


def fallback_notes(fits, min_windows: int, split: str) -> list[str]:
    """What the patterns with fewer than ``min_windows`` windows got instead of their own fit."""
    notes = []
    pooled = [fit.pattern for fit in fits if fit.pooled]
    if pooled:
        notes.append(
            f"the pooled fit of every pattern (fewer than min_windows={min_windows} {split} windows): "
            + ", ".join(pooled)
        )
    kept = [fit.pattern for fit in fits if not fit.fitted and not fit.pooled]
    if kept:
        notes.append(
            f"kept at 1 (fewer than min_windows={min_windows} {split} windows, even all patterns "
            f"together): {', '.join(kept)}"
        )
    return notes


def main(argv: list[str]) -> int:
    command = parse_config_command(
        argv,
        "calibrate",
        "mmf-rl calibrate",
        "Fit a trained model's forecast scale per presence pattern on its validation split "
        "and store the factors with the model.",
        EXAMPLES,
    )
    try:
        cfg = command.compose("calibrate")
        if command.print_config:
            print(OmegaConf.to_yaml(cfg), end="")
            return 0
        if cfg.get("checkpoint") is None:
            raise ConfigError(f"checkpoint=PATH is required: {TRAINED_MODEL_KINDS}")
        summary = run_calibration(cfg)
    except (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError, TypeError) as err:
        return report_command_error("mmf-rl calibrate", err)
    print(
        f"{summary['checkpoint']}: forecast scale factors fitted on the {summary['split']} split "
        f"(method={summary['method']})\n"
    )
    print(summary["table"])
    for note in summary["notes"]:
        print(f"\nNote: {note}")
    for path in summary["written"]:
        print(f"written: {path}")
    return 0
