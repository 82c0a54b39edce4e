"""Train and score the runs of a comparison, resuming: a run whose ``eval/window_errors.json`` exists
is complete and reused.

Each run is trained with ``mmf_rl.train`` (``mmf-rl train``), evaluated on every presence subset of
its test split with ``mmf_rl.evaluate`` (``mmf-rl eval``), and then run over the test windows once
more to keep every window's squared error with its episode, which the paired bootstrap needs, and over
a draw of training windows for its fit.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import statistics
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from mmf_rl.compare.entries import Entry, Study, run_plan, subsets

logger = logging.getLogger(__name__)


def train_overrides(
    entry: Entry, seed: int, study: Study, run_dir: Path, extra: tuple[str, ...] = ()
) -> list[str]:
    budget = study.budget
    size = [] if budget.image_size is None else [f"data.image_size=[{budget.image_size},{budget.image_size}]"]
    return [
        *entry.overrides,
        *extra,
        *study.data_overrides,
        f"data.cache_dir={study.out / 'cache'}",
        *size,
        f"run_dir={run_dir}",
        f"trainer.total_steps={budget.steps}",
        f"trainer.batch_size={budget.batch_size}",
        f"trainer.seed={seed}",
        f"trainer.eval_every={budget.steps}",
        f"trainer.checkpoint_every={budget.steps}",
        f"trainer.warmup_steps={min(100, budget.steps // 10)}",
        "trainer.keep_checkpoints=1",
        "trainer.progress_bar=false",
        "logger=csv",
        "num_workers=2",
        f"device={study.device}",
    ]


def compose_train(entry: Entry, seed: int, study: Study, run_dir: Path, extra: tuple[str, ...] = ()):
    """The training config of one run: ``train_overrides`` composed, with the budget's KL warm-up where
    the entry's loss reads one (the ELBO's with ``loss.kl_weight > 0``: the paper model, MVAE); not for
    LF-LSTM's or MulT's NLL, whose trainer refuses a loss setting its terms do not read. The warm-up is
    set on the composed config: whether it is read depends on the model and on the whole loss config
    (``loss=no_mis``, ``loss.kl_weight=0``, ``loss.terms``), which only the composition knows."""
    from mmf_rl.configuration import compose_config, to_container
    from mmf_rl.models import loss_settings_read
    from mmf_rl.objectives import LossConfig

    cfg = compose_config(
        "train", train_overrides(entry, seed, study, run_dir, extra), list(study.config_dirs)
    )
    loss_cfg = LossConfig.from_dict(to_container(cfg.loss))
    if "kl_warmup_steps" in loss_settings_read(to_container(cfg.model), loss_cfg):
        cfg.loss.kl_warmup_steps = min(200, study.budget.steps // 5)
    return cfg


def open_data(study: Study):
    """Build (or open) the window cache once before the first training, so no run's time includes it.

    Args:
        study (Study): the comparison (its first entry's data config, its cache directory).

    Returns:
        The dataset (its splits name the test episodes).
    """
    from mmf_rl.configuration import to_container
    from mmf_rl.datasets import DataConfig, WindowDataset

    cfg = compose_train(study.entries[0], 0, study, study.out / "cache")
    return WindowDataset(DataConfig.from_dict(to_container(cfg.data)), num_workers=2)


def check_entries(study: Study) -> None:
    """Compose every entry's training config before the first training: an option this build lacks, or
    a loss option the entry's model does not train with, fails here in seconds, naming the entry, not
    after an hour of runs.

    Args:
        study (Study): the comparison.

    Raises:
        ValueError: entries whose config does not compose or sets what their model ignores (each
            named, with the reason).
    """
    from mmf_rl.configuration import to_container
    from mmf_rl.models import check_loss_settings
    from mmf_rl.objectives import LossConfig, default_loss_config

    defaults = default_loss_config(study.config_dirs)
    problems = []
    for entry in study.entries:
        try:
            cfg = compose_train(entry, 0, study, study.out / "check")
            loss_cfg = LossConfig.from_dict(to_container(cfg.loss))
            check_loss_settings(to_container(cfg.model), loss_cfg, defaults)
        except ValueError as err:  # a ConfigError, or a bad value of the loss config
            problems.append(f"{entry.label!r} ({' '.join(entry.overrides)}): {' '.join(str(err).split())}")
    if problems:
        raise ValueError(
            "these entries do not compose with this build's configs, or set what their model ignores:\n  "
            + "\n  ".join(problems)
            + "\nleave them out with --entries, or add the option they set (remove one their model ignores)"
        )


# Where a run lives and what runs it: a run copied or moved to another ``--out`` is still the same run.
PLACE_SETTINGS = frozenset({"run_dir", "data.cache_dir", "device", "num_workers"})


def check_reused(study: Study) -> None:
    """A completed run in ``study.out`` trained with another budget, or with a config other than the one
    this build composes for it (an entry's options, or a default changed since), would silently mix
    models in one table: refused, naming the runs and the settings.

    Args:
        study (Study): the comparison.

    Raises:
        ValueError: such runs (up to 12 named, with how each differs).
    """
    plans = {
        run_dir: (trained, seed, extra)
        for e in study.entries
        for trained, seed, run_dir, extra, _ in run_plan(e, study)
    }
    stale = [
        f"{run_dir}: {reason}"
        for run_dir, (trained, seed, extra) in plans.items()
        if (reason := stale_reason(trained, seed, study, run_dir, extra))
    ]
    if stale:
        shown = stale[:12] + ([f"... and {len(stale) - 12} more"] if len(stale) > 12 else [])
        raise ValueError(
            f"{study.out} holds completed runs that this comparison would not train "
            f"({study.budget.steps} steps of batch {study.budget.batch_size}, each entry's config as this "
            "build composes it):\n  " + "\n  ".join(shown) + "\nuse another --out, or delete those runs "
            "to train them again"
        )


def stale_reason(entry: Entry, seed: int, study: Study, run_dir: Path, extra: tuple[str, ...]) -> str:
    """How the completed run in ``run_dir`` differs from the one this comparison would train there
    (empty: it does not, or the run is not complete)."""
    from mmf_rl.trainers.training import describe_trained_differently, trained_differently

    if (r := completed(run_dir)) is None:
        return ""
    if (r["steps"], r["batch_size"]) != (study.budget.steps, study.budget.batch_size):
        return f"{r['steps']} steps of batch {r['batch_size']}"
    changed = trained_differently(run_dir, compose_train(entry, seed, study, run_dir, extra), PLACE_SETTINGS)
    return describe_trained_differently(changed, limit=4)


def trained_model_and_data(run_dir: Path, device: str):
    """A run's last checkpoint (eval mode) and its windows, normalised with the checkpoint's statistics."""
    from mmf_rl.datasets import DataConfig, WindowDataset
    from mmf_rl.datasets.splits import Normalizer
    from mmf_rl.models import load_trained_model

    model, stats, data_config = load_trained_model(run_dir / "checkpoints", map_location=device)
    data = WindowDataset(DataConfig.from_dict(data_config))
    data.normalizer = Normalizer(stats)
    return model, data


def window_errors(run_dir: Path, device: str, batch_size: int = 256) -> dict[str, dict[str, list]]:
    """Every test window's squared error (mean over ``T x D``, normalised target) per presence subset,
    with its window id and episode: ``{subset: {"window", "episode", "squared_error"}}``.

    The windows and normalisation are those of ``mmf-rl eval`` (the test split in order, the
    checkpoint's statistics); ``run_one`` checks the means agree with its MSE.

    Args:
        run_dir (Path): a trained run (its ``checkpoints/``).
        device (str): where the model runs.
        batch_size (int, optional): windows per forward pass. Defaults to ``256``.

    Returns:
        ``{subset: {"window": [...], "episode": [...], "squared_error": [...]}}`` for the subsets with
        a window.
    """
    return scored_windows(*trained_model_and_data(run_dir, device), device, batch_size)


@torch.no_grad()
def scored_windows(model, data, device: str, batch_size: int = 256) -> dict[str, dict[str, list]]:
    """:func:`window_errors` of a loaded model and its windows."""
    out = {}
    for name, subset in subsets([s.name for s in data.specs]):  # the trained data's modalities
        rows = subset_errors(model, data, subset, device, batch_size)
        if rows["window"]:
            out[name] = rows
    return out


def subset_errors(
    model, data, subset: dict[str, bool], device: str, batch_size: int, split: str = "test", windows=None
) -> dict[str, list]:
    """Every window's squared error under ``subset`` on ``split`` (its windows, or the given ones)."""
    from mmf_rl import keys
    from mmf_rl.datasets import apply_presence_subset

    rows: dict[str, list] = {"window": [], "episode": [], "squared_error": []}
    for chunk in (data.split_windows[split] if windows is None else windows).split(batch_size):
        batch = data.batch(chunk, split)
        # apply_presence_subset keeps the windows that still have one of the subset's modalities.
        kept = torch.zeros(len(chunk), dtype=torch.bool)
        for m, keep in subset.items():
            kept |= batch.get(keys.present_key(m)) & keep
        batch = apply_presence_subset(batch, subset).to(device)
        if batch.shape[0] == 0:
            continue
        loc = model(batch.clone(False)).get(keys.FORECAST_LOC)
        rows["window"] += chunk[kept].tolist()
        rows["episode"] += data.window_episode[chunk[kept]].tolist()
        rows["squared_error"] += ((loc - batch.get(keys.TARGET)) ** 2).mean((1, 2)).cpu().tolist()
    return rows


# Training windows a run's fit is scored on: enough for a stable mean, a few seconds of forward passes.
FIT_WINDOWS = 2000


def train_mse(run_dir: Path, device: str, windows: int = FIT_WINDOWS, batch_size: int = 256) -> float:
    """The point forecast's MSE (normalised target, every sensor the data has) on up to ``windows``
    training windows, drawn once with a generator seeded 0 (the same windows for every run of a
    recording). Beside the test MSE it tells a model that does not fit its training windows from one
    that fits them and does not generalise."""
    return training_windows_mse(*trained_model_and_data(run_dir, device), device, windows, batch_size)


@torch.no_grad()
def training_windows_mse(
    model, data, device: str, windows: int = FIT_WINDOWS, batch_size: int = 256
) -> float:
    """:func:`train_mse` of a loaded model and its windows."""
    train = data.split_windows["train"]
    drawn = train[torch.randperm(len(train), generator=torch.Generator().manual_seed(0))[:windows]]
    every_sensor = dict.fromkeys((spec.name for spec in data.specs), True)
    errors = subset_errors(model, data, every_sensor, device, batch_size, "train", drawn)["squared_error"]
    return statistics.fmean(errors)


def evaluate_run(run_dir: Path, seed: int, device: str) -> dict:
    from mmf_rl.eval.evaluation import evaluate

    overrides = [
        f"checkpoint={run_dir}",
        "plots=false",
        "num_samples=0",
        f"device={device}",
        f"out_dir={run_dir / 'eval'}",
        f"seed={seed}",
    ]
    return evaluate(overrides=overrides)


def check_agreement(run_dir: Path, errors: dict[str, dict[str, list]], summary: dict) -> None:
    for name, rows in errors.items():
        mse = statistics.fmean(rows["squared_error"])
        reported = summary["subsets"][name]["mse"]
        if abs(mse - reported) > 1e-4 * max(abs(reported), 1e-8) + 1e-7:
            raise RuntimeError(
                f"{run_dir}: subset {name}: the per-window errors average {mse:.6g} but "
                f"the evaluation reports MSE {reported:.6g}; the two passes disagree on windows "
                "or normalisation"
            )


def run_one(entry: Entry, seed: int, study: Study, run_dir: Path, extra: tuple[str, ...] = ()) -> dict:
    """Train one model, evaluate it, keep its per-window errors in ``window_errors.json`` (written last:
    its presence marks the run complete). An interrupted run's directory is removed first.

    Args:
        entry (Entry): the entry trained.
        seed (int): its training seed.
        study (Study): the comparison (budget, data, device).
        run_dir (Path): where the run goes.
        extra (tuple[str, ...], optional): more overrides (a retrained run's removed modalities).

    Returns:
        What ``window_errors.json`` holds: timings, the budget, the constant-velocity reference, each
        subset's per-window errors and the training-window MSE.
    """
    from mmf_rl.eval.report import write_json
    from mmf_rl.trainers.training import train

    if run_dir.exists():  # an interrupted run: start it again
        shutil.rmtree(run_dir)
    start = time.perf_counter()
    train(compose_train(entry, seed, study, run_dir, extra))
    trained = time.perf_counter() - start
    summary = evaluate_run(run_dir, seed, study.device)
    model, data = trained_model_and_data(run_dir, study.device)  # loaded once for both passes
    errors = scored_windows(model, data, study.device)
    check_agreement(run_dir, errors, summary)
    fit = training_windows_mse(model, data, study.device)
    total = time.perf_counter() - start
    budget = study.budget
    step_seconds = budget.batch_size / training_rate(run_dir)
    result = {
        "train_seconds": trained,
        "seconds": total,
        "step_seconds": step_seconds,
        "jobs": study.jobs,  # runs trained at once: their per-run times overlap
        "steps": budget.steps,
        "batch_size": budget.batch_size,
        "constant_velocity": summary.get("constant_velocity"),
        "subsets": errors,
        "train_mse": fit,
    }
    write_json(run_dir / "eval" / "window_errors.json", result)  # last: its presence marks the run complete
    logger.info(
        "%s %s seed %d: trained %d steps in %.0f s (%.0f ms/step in the training loop), total with setup "
        "and evaluation %.0f s",
        entry.label, " ".join(extra), seed, budget.steps, trained, 1e3 * step_seconds, total,
    )  # fmt: skip
    return result


def training_rate(run_dir: Path) -> float:
    """Samples per second of the whole training loop: the last ``train/samples_per_s`` the trainer
    logged (csv logger), which counts from the first step to the last."""
    path = run_dir / "logs" / "scalars" / "train" / "samples_per_s.csv"
    rows = path.read_text().split()
    if not rows:
        raise RuntimeError(f"{path} is empty: the training logged no throughput")
    return float(rows[-1].split(",")[1])


def completed(run_dir: Path) -> dict | None:
    path = run_dir / "eval" / "window_errors.json"
    return json.loads(path.read_text()) if path.is_file() else None


def run_pending(study: Study) -> tuple[int, int]:
    """Train and score every run the entries need that no earlier invocation completed, ``study.jobs``
    at a time (a failed run stops the comparison with its error).

    Args:
        study (Study): the comparison.

    Returns:
        ``(runs needed, runs reused)``.
    """
    runs = {}
    for entry in study.entries:
        for trained, seed, run_dir, extra, _ in run_plan(entry, study):
            runs.setdefault(run_dir, (trained, seed, study, run_dir, extra))
    pending = [task for run_dir, task in runs.items() if completed(run_dir) is None]
    if study.jobs == 1:
        for task in pending:
            run_one(*task)
    else:
        run_in_processes(pending, study.jobs)
    return len(runs), len(runs) - len(pending)


def run_in_processes(tasks: Sequence[tuple], jobs: int) -> None:
    """``run_one`` over ``tasks``, ``jobs`` processes at once. Small models use two threads poorly: one
    thread a run and one run a core keeps the cores busy. Each run writes only its own run_dir."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    threads = max(1, (os.cpu_count() or 1) // jobs)
    shown = logging.getLogger("mmf_rl")
    log_level = shown.getEffectiveLevel() if shown.handlers else None
    with ProcessPoolExecutor(
        jobs,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=start_worker,
        initargs=(threads, log_level),
    ) as pool:
        futures = [pool.submit(run_one, *task) for task in tasks]
        for future in futures:
            future.result()  # a failed run stops the comparison with its error


def start_worker(threads: int, log_level: int | None) -> None:
    """A worker of ``run_in_processes``: ``threads`` torch threads, and the parent's progress messages
    shown as the parent shows them (a spawned process starts without the CLI's logging setup)."""
    torch.set_num_threads(threads)
    if log_level is not None:
        from mmf_rl.log import configure_logging

        configure_logging(log_level)
