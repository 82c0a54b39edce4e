"""`mmf-rl calibrate checkpoint=DIR [split=val] [method=levels] [per_step=false] [min_windows=32]`:
recalibrate a trained model's forecast scale per presence pattern, on held-out windows, and store the
factors with the model.

    mmf-rl calibrate checkpoint=runs/forecaster              # fit on its val split, write back
    mmf-rl eval checkpoint=runs/forecaster                   # then scores the calibrated model

``checkpoint`` is what ``mmf-rl eval`` takes (a run directory, its ``checkpoints/``, one checkpoint
or a ``save_pretrained`` directory), opened on its own data config and normalisation statistics
(``data_root`` when the dataset is elsewhere). The factors are fitted in closed form from the
uncalibrated scale (:mod:`mmf_rl.eval.scale_fit`; a refit replaces earlier factors), by ``method``:

* ``levels`` (the default): a factor per pattern whose 90% intervals cover 90% of the split's
  values, and a level curve per pattern: the intervals at every level from 10% to 99% cover their
  level of the split's values, whatever the errors' shape. ``eval``'s coverage, width and CRPS read
  the curve; the NLL (and everything else that reads one scale) stays the family at the 90% scale.
* ``coverage``: the 90% factor alone; the family's shape sets the other levels (on errors heavier-
  tailed than the family, the 50% intervals over-cover).
* ``temperature``: the NLL-optimal temperature, which heavy-tailed errors inflate.

``per_step=true`` also fits each horizon step of a pattern (errors that grow with the horizon faster
than the scale does; a pattern with fewer than ``min_windows`` windows keeps the pooled factor, and
curve, at every step). They are printed as a table (pattern, windows, factor, with ``per_step`` each
step's, with ``levels`` the curve: the half width at each level over the family's; 50% and 90%
coverage on the split before -> after), and written atomically into the checkpoint (re-saved at its
step) or the ``save_pretrained`` directory, and into the run's other copy of the same weights
(``RUN_DIR/model`` or the last checkpoint). A later ``mmf-rl eval`` uses them without any flag, and
its results say so.

From Python: :func:`mmf_rl.eval.calibration.calibrate`, which returns what the command prints.

``split=test`` is refused: a calibration fitted on the test futures would score itself.
"""

from __future__ import annotations

from mmf_rl.checkpoint import CheckpointError
from mmf_rl.configuration import ConfigError, run_config_command
from mmf_rl.eval.calibration import calibrate

EXAMPLES = [
    "mmf-rl calibrate checkpoint=runs/forecaster                 # its val split; then mmf-rl eval",
    "mmf-rl calibrate checkpoint=exports/g1 data_root=/data/g1 min_windows=64",
    "mmf-rl calibrate checkpoint=runs/forecaster method=temperature   # the NLL-optimal temperature",
    "mmf-rl calibrate checkpoint=runs/forecaster per_step=true        # and a factor per horizon step",
    "mmf-rl calibrate checkpoint=runs/forecaster method=coverage      # the 90% factor alone",
]


def show(fitted: dict) -> None:
    """The factors fitted per presence pattern, notes on the patterns fitted together, the files written."""
    print(
        f"{fitted['checkpoint']}: forecast scale factors fitted on the {fitted['split']} split "
        f"(method={fitted['method']}{', per horizon step' if fitted['per_step'] else ''})\n"
    )
    print(fitted["table"])
    for note in fitted["notes"]:
        print(f"\nNote: {note}")
    for path in fitted["written"]:
        print(f"written: {path}")


def main(argv: list[str]) -> int:
    return run_config_command(
        argv,
        "calibrate",
        "Fit a trained model's forecast scale per presence pattern on its validation split and store "
        "the factors with the model.",
        EXAMPLES,
        calibrate,
        (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError, TypeError),
        show,
    )
