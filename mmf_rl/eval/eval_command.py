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

From Python: ``mmf_rl.evaluate`` (:func:`mmf_rl.eval.evaluation.evaluate`), which returns the
summary written to ``results.json``.

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

from mmf_rl.checkpoint import CheckpointError
from mmf_rl.configuration import ConfigError, run_config_command
from mmf_rl.eval.evaluation import evaluate, headers

EXAMPLES = [
    "mmf-rl eval checkpoint=runs/forecaster                  # the run's last checkpoint, its test split",
    "mmf-rl eval checkpoint=runs/forecaster split=val num_samples=50 plots=false",
    "mmf-rl eval checkpoint=runs/forecaster eval_latent=predictive predictive_samples=32",
    "mmf-rl eval checkpoint=exports/g1 data_root=/data/g1     # save_pretrained dir -> exports/g1/eval",
]


def show(summary: dict) -> None:
    """The results table as ``results.md`` holds it, then the plots written."""
    print(f"{headers(summary)}{summary['table']}")
    for path in summary["plots"]:
        print(f"plot: {path}")


def main(argv: list[str]) -> int:
    return run_config_command(
        argv,
        "eval",
        "Score a trained forecaster on every presence subset of its dataset's test split: table, "
        "results.json and plots.",
        EXAMPLES,
        evaluate,
        (ConfigError, CheckpointError, FileNotFoundError, ValueError, KeyError),
        show,
    )
