"""A training run from a composed train config: what ``mmf-rl train`` runs, and :func:`train`, its
Python entry point (``mmf_rl.train``).

The composed config is typed once, by :class:`TrainRunConfig`, where the run starts; every step
below reads that. Top to bottom: set up devices and processes, open the window cache, build the
model and its losses, train with checkpoints, logs and validation, then save the final weights
(the command's documentation, :mod:`mmf_rl.trainers.train_command`, says what each setting does).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf

from mmf_rl.checkpoint import CheckpointError, list_checkpoints, load_checkpoint, remove_leftovers
from mmf_rl.configuration import (
    ConfigError,
    config_changes,
    config_or_overrides,
    load_config,
    save_config,
    to_container,
)
from mmf_rl.datasets import AugmentConfig, DataConfig, TrainingAugmentation, WindowDataset
from mmf_rl.devices import resolve_device
from mmf_rl.eval.metrics import evaluate_forecasts
from mmf_rl.eval.scale_fit import calibrate_after_training, save_to_checkpoint
from mmf_rl.models import (
    build_loss,
    build_model,
    check_loss_settings,
    init_weights_from,
    loss_settings_read,
    saved_config,
)
from mmf_rl.models.encoders import check_encoder
from mmf_rl.models.loading import RUN_EXPORT_DIR
from mmf_rl.models.registry import DEFAULT_MODEL, model_settings_from_group
from mmf_rl.objectives import LossConfig, default_loss_config, resolve_observed_dropout
from mmf_rl.trainers.latent_sampler import SamplerConfig, check_sampler_settings, train_latent_sampler
from mmf_rl.trainers.trainer import Trainer, TrainerConfig, seed_everything

logger = logging.getLogger(__name__)

RUN_CONFIG = "config.yaml"
PRETRAINED_DIR = RUN_EXPORT_DIR  # run_dir/model: the final weights as save_pretrained writes them
# Keys that may differ between a run and its resumption (run_dir: the run may have been moved).
RESUMABLE_CHANGES = {
    "resume",
    "trainer.progress_bar",
    "trainer.prefetch",
    "augment.workers",
    "logger",
    "num_workers",
    "run_dir",
}


def init_distributed(device: torch.device) -> tuple[int, int]:
    """Join the process group torchrun describes (``WORLD_SIZE``/``RANK``); (0, 1) when alone."""
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    if world_size == 1:
        return 0, 1
    backend = "nccl" if device.type == "cuda" else "gloo"
    # A bounded timeout: if a rank dies, the others fail in a collective instead of hanging forever.
    dist.init_process_group(
        backend, timeout=timedelta(seconds=int(os.environ.get("MMF_RL_DIST_TIMEOUT", "300")))
    )
    if device.type == "cuda":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    return dist.get_rank(), world_size


def make_logger(kind: str, run_dir: Path):
    if kind == "none":
        return None
    from torchrl.record.loggers import get_logger

    if kind not in ("csv", "tensorboard", "wandb"):
        raise ValueError(f"logger must be one of csv, tensorboard, wandb, none; found {kind!r}")
    return get_logger(kind, logger_name=str(run_dir), experiment_name="logs")


def _logged_step(line: str) -> int | None:
    """The step of a complete ``step,value`` row; None for a row cut short by a kill."""
    fields = line.rstrip("\n").split(",")
    try:
        if not line.endswith("\n") or len(fields) != 2 or not math.isfinite(float(fields[0])):
            return None
        float(fields[1])
    except ValueError:
        return None
    return int(float(fields[0]))


def truncate_csv_logs(log_dir: Path, step: int) -> None:
    """Drop the rows logged after ``step`` from torchrl's CSV scalars (``<log_dir>/scalars/**.csv``,
    ``step,value`` lines): a run killed after its last checkpoint logged steps that the resumed run
    logs again (and maybe half a row). Each file is rewritten atomically (temp + rename)."""
    for path in sorted((log_dir / "scalars").rglob("*.csv")):
        lines = path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if (logged := _logged_step(line)) is not None and logged <= step]
        if len(kept) != len(lines):
            tmp = path.with_name(f".{path.name}.tmp")
            tmp.write_text("".join(kept))
            os.replace(tmp, path)


def trained_differently(run_dir: Path, cfg: DictConfig, ignore=frozenset()) -> dict[str, tuple]:
    """The settings the run in ``run_dir`` trained with another value than ``cfg`` (composed now) holds,
    ``{dotted key: (trained, now)}``: the run is not the one ``cfg`` would train. Left out: ``ignore``,
    settings a newer mmf-rl added (their defaults keep the old behaviour), and loss settings the
    model's terms do not read (``L_mis``'s for LF-LSTM)."""
    current = to_container(cfg)
    read = loss_settings_read(current["model"], LossConfig.from_dict(current["loss"])) | {"terms"}
    unread = {f"loss.{name}" for name in current["loss"] if name not in read}
    saved = OmegaConf.to_container(load_config(run_dir / RUN_CONFIG))
    return config_changes(saved, current, set(ignore) | unread)[1]


def describe_trained_differently(changed: dict[str, tuple], limit: int | None = None) -> str:
    """``trained_differently``'s result as one line, its first ``limit`` settings (all: ``None``)."""
    shown = list(changed.items())[:limit]
    return ", ".join(f"trained with {k}={old!r} (now {new!r})" for k, (old, new) in shown)


def check_name(name: str) -> None:
    """``name`` becomes a directory name (``run_dir: runs/${name}``): one path component, no traversal."""
    if any(sep in name for sep in (os.sep, os.altsep) if sep) or name in ("", ".", ".."):
        raise ConfigError(
            f"name={name!r} must be a plain name without path separators (it names the run "
            "directory runs/<name>); to train elsewhere set run_dir=PATH instead"
        )


@dataclass(frozen=True)
class TrainRunConfig:
    """A training run's settings, typed once from the composed train config (:meth:`from_config`):
    all that the run's steps read.

    Args:
        name: the run's name (``run_dir: runs/${name}`` by default).
        run_dir: where the run writes, resolved.
        resume: continue the run in ``run_dir`` from its last checkpoint.
        init_from: a run, checkpoint or save_pretrained directory to fine-tune from (weights only).
        calibrate: fit the forecast scale per presence pattern on val after training.
        device: ``cpu``, ``cuda`` or ``auto``.
        logger: ``csv``, ``tensorboard``, ``wandb`` or ``none``.
        num_workers: cache-building processes (``None``: one per core).
        model: the model group as plain data (its fields depend on ``model.name``).
        data: the data group.
        trainer: the trainer group.
        loss: the loss group.
        augment: the augment group (training batches' augmentation).
        sampler: the learned sampler's training (``model.learned_samples=K``).
        settings: the whole config as plain data, ``run_dir`` resolved: what the run saves as
            ``config.yaml`` and puts in its checkpoints, and what a resume is compared with.
    """

    name: str
    run_dir: Path
    resume: bool
    init_from: str | None
    calibrate: bool
    device: str
    logger: str
    num_workers: int | None
    model: dict
    data: DataConfig
    trainer: TrainerConfig
    loss: LossConfig
    augment: AugmentConfig
    sampler: SamplerConfig
    settings: dict

    @classmethod
    def from_config(cls, cfg: DictConfig) -> TrainRunConfig:
        """Type a composed train config; a bad name or group is an error before anything is made."""
        check_name(str(cfg.name))
        # Relative paths and '..' are the user's choice; the saved config and the messages show where
        # they really lead.
        settings = {**to_container(cfg), "run_dir": str(Path(cfg.run_dir).resolve())}

        def group(key: str) -> dict | None:  # its own copy: nothing read from a group edits `settings`
            return to_container(cfg[key]) if key in cfg else None

        return cls(
            name=settings["name"],
            run_dir=Path(settings["run_dir"]),
            resume=settings["resume"],
            init_from=settings.get("init_from"),
            calibrate=settings["calibrate"],
            device=settings["device"],
            logger=settings["logger"],
            num_workers=settings["num_workers"],
            model=group("model"),
            data=DataConfig.from_dict(group("data")),
            trainer=TrainerConfig.from_dict(group("trainer")),
            loss=LossConfig.from_dict(group("loss")),
            augment=AugmentConfig.from_dict(group("augment")),
            sampler=SamplerConfig.from_dict(group("sampler")),
            settings=settings,
        )


def check_resumable(run: TrainRunConfig) -> None:
    """``run`` may resume the run in its ``run_dir``: that run exists and trained with the same config
    (but for :data:`RESUMABLE_CHANGES`)."""
    saved_path = run.run_dir / RUN_CONFIG
    if not saved_path.is_file():
        raise CheckpointError(
            f"resume=true but {saved_path} does not exist: nothing to resume in {run.run_dir}"
        )
    saved = OmegaConf.to_container(load_config(saved_path))
    added, changed = config_changes(saved, run.settings, RESUMABLE_CHANGES)
    # Settings a newer mmf-rl added since the run started: the saved config cannot hold them, and
    # refusing them would make every run unresumable after an upgrade. They are taken as composed
    # now (their defaults, unless set on this command line) and named; but the model's are read as
    # the saved model's (resumed_run): it continues the model it trained.
    if added:
        model = model_settings_from_group(saved.get("model", {}), saved=True)
        used = {
            k: model.get(k.removeprefix("model."), v) if k.startswith("model.") else v
            for k, v in added.items()
        }
        warnings.warn(
            f"resuming {run.run_dir}: its {saved_path.name} predates the settings "
            + ", ".join(f"{k}={v!r}" for k, v in used.items())
            + "; the resumed run uses these values (a model setting: the value describing the model the run "
            "trained, not today's default)",
            stacklevel=2,
        )
    if changed:
        details = ", ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in list(changed.items())[:8])
        raise CheckpointError(
            f"resume=true with a config that differs from {saved_path} ({details}); resume with "
            "the same config, or train into a new run_dir"
        )


def resumed_run(run: TrainRunConfig) -> TrainRunConfig:
    """``run`` as it resumes the run in its ``run_dir``: with the model group that run saved
    (``config.yaml``), which :func:`build_model_and_loss` reads as a saved model's (``build_model(...,
    saved=True)``, :func:`~mmf_rl.models.registry.config_from_saved`), so that a model setting added to
    mmf-rl since the run began takes the value describing the model it trained (e.g. ``decoder_input=
    tokens``), not today's default composed now. :func:`check_resumable` has compared every other
    setting with the saved ones."""
    saved = OmegaConf.to_container(load_config(run.run_dir / RUN_CONFIG))
    model = saved.get("model", run.model)
    return dataclasses.replace(run, model=model, settings={**run.settings, "model": model})


def prepare_run_dir(run: TrainRunConfig, rank: int) -> TrainRunConfig:
    """On rank 0: ``run_dir`` cleaned of a killed save's leftovers, checked against the run it would
    resume or overwrite, and given the config. Returns the run to train: a resumed run's
    (:func:`resumed_run`) on every rank."""
    if rank == 0:
        for leftover in remove_leftovers(run.run_dir / "checkpoints"):
            logger.info("removed %s: left by a run killed while saving or pruning a checkpoint", leftover)
        if run.resume:
            check_resumable(run)
        elif list_checkpoints(run.run_dir / "checkpoints"):
            raise CheckpointError(
                f"{run.run_dir} already holds a trained run; pass resume=true to continue it, or "
                "choose another run_dir (nothing was overwritten)"
            )
    trained = resumed_run(run) if run.resume else run
    if rank == 0:
        save_config(trained.settings, run.run_dir / RUN_CONFIG)
    return trained


def open_windows(run: TrainRunConfig, world_size: int) -> WindowDataset:
    """The window cache of the run's data config, built by one process per machine."""
    for name, modality in run.data.modalities.items():  # before the window cache is built
        if modality.encoder is not None:
            check_encoder(name, modality.encoder, modality.kind)
    # One process per machine builds the cache (or waits on the cache directory's lock for
    # another machine's build on a shared filesystem); the others open it after the barrier.
    builder = int(os.environ.get("LOCAL_RANK", "0")) == 0
    if builder:
        data = WindowDataset(run.data, num_workers=run.num_workers)
        logger.info("window cache %s: %s", "built" if data.built else "opened", data.cache_path)
    if world_size > 1:
        dist.barrier()
    if not builder:
        with warnings.catch_warnings():  # the builder already warned about absent modalities
            warnings.simplefilter("ignore")
            data = WindowDataset(run.data)
    return data


def build_model_and_loss(run: TrainRunConfig, data: WindowDataset, rank: int, device):
    """The model on ``device`` (the same initial weights on every rank, or those of ``init_from``),
    its name and its loss module."""
    seed_everything(run.trainer.seed)  # same initial weights on every rank
    model = build_model(
        run.model,
        data.specs,
        data.config.history,
        data.config.horizon,
        data.target_dim,
        action_shape=data.action_shape,
        saved=run.resume,  # a resumed run rebuilds the model it trained (resumed_run)
    ).to(device)
    model_name = run.model.get("name", DEFAULT_MODEL)
    if run.init_from is not None and not run.resume:  # resuming restores the run's own weights
        source = init_weights_from(model, run.init_from)
        if rank == 0:
            logger.info("fine-tuning from %s: weights copied, new optimizer, step 0", source)
    # The settings were checked by check_loss_settings_read (a new run) or are the run's own (resumed).
    absent = {name: outages["fraction"] for name, outages in data.observed_outages.items()}
    loss = build_loss(model_name, model, resolve_observed_dropout(run.loss, absent), check_unread=False)
    return model, model_name, loss


def check_loss_settings_read(run: TrainRunConfig) -> None:
    """A new run may not carry a loss setting that its model's loss terms do not read (e.g.
    ``loss.best_of_k_weight`` with ``model=lf_lstm``, ``loss.dropped_prior_weight`` without
    ``model.prior=learned``): training would silently ignore it. Compared with what the loss config group
    gives without asking (its KL warm-up is every model's, read by the ELBO's only), before the run
    directory and the window cache are made. A resumed run is not checked: it continues as it began, and
    one begun before this check may hold such a setting, which changed nothing in it."""
    if not run.resume:
        check_loss_settings(run.model, run.loss, default_loss_config())


def training_augmentation(run: TrainRunConfig, data: WindowDataset) -> TrainingAugmentation | None:
    """The run's augmentation of training batches (``augment`` group), ``None`` when it does nothing."""
    if run.augment.enable or run.augment.rotation:
        return TrainingAugmentation(run.augment, data.specs, run.trainer.seed)
    return None


def make_trainer(run: TrainRunConfig, model, model_name: str, loss, data: WindowDataset, ranks, device):
    """The `Trainer` of the run: its train loader (augmented if configured), validation on the val
    split, checkpoints that carry the config and the normalisation statistics."""
    rank, world_size = ranks
    trainer_cfg = run.trainer
    seed_everything(trainer_cfg.seed + rank)  # then each rank draws its own latents
    loader = data.loader(
        "train",
        trainer_cfg.batch_size,
        seed=trainer_cfg.seed,
        rank=rank,
        world_size=world_size,
        augment=training_augmentation(run, data),
    )
    val_loader = data.loader("val", max(trainer_cfg.batch_size, 256))
    denormalize = data.normalizer.denormalize_target

    def validate(m):
        metrics = evaluate_forecasts(
            m, (b.to(device) for b in val_loader), lambda t: denormalize(t.cpu()).to(t)
        )
        return {f"val/{k}": v for k, v in metrics.items() if k != "windows"}

    return Trainer(
        model,
        loss,
        loader,
        trainer_cfg,
        run_dir=run.run_dir,
        logger=make_logger(run.logger, run.run_dir) if rank == 0 else None,
        evaluate=validate if len(data.split_windows["val"]) else None,
        checkpoint_meta={
            "config": run.settings,
            "model_config": saved_config(model_name, model),
            "data_fingerprint": data.cache_path.name,
            "world_size": world_size,
        },
        checkpoint_tensors=data.normalizer.stats,
        rank=rank,
        world_size=world_size,
    )


def save_trained_model(
    run: TrainRunConfig, model, data: WindowDataset, trainer: Trainer, metrics: dict, device
) -> None:
    """The trained model with what it needs to forecast (statistics, data config, scale factors
    unless ``calibrate=false``), ready for from_pretrained / push_to_hub, in ``run_dir/model``."""
    model.normalization_stats, model.data_config = data.normalizer.stats, data.config.to_dict()
    if getattr(model, "latent_sampler", None) is not None:
        train_sampler_once(run, model, data, trainer)
    if run.calibrate:
        logger.info("%s", calibrate_after_training(model, data, trainer.last_checkpoint, device))
    model.save_pretrained(run.run_dir / PRETRAINED_DIR)
    summary = ", ".join(f"{k}={v:.4g}" for k, v in metrics.items())
    logger.info(
        "trained %d steps -> %s%s",
        trainer.step,
        trainer.last_checkpoint,
        f" ({summary})" if summary else "",
    )


def train_sampler_once(run: TrainRunConfig, model, data: WindowDataset, trainer: Trainer) -> None:
    """Train the model's learned sampler after the forecaster and store it in the last checkpoint, unless
    that checkpoint already holds it trained with these settings (a resumed run that had finished)."""
    settings = dataclasses.asdict(run.sampler)
    if load_checkpoint(trainer.last_checkpoint).meta.get("learned_sampler") == settings:
        logger.info("learned sampler already trained in %s", trainer.last_checkpoint)
        return
    augment = training_augmentation(run, data)
    logger.info("%s", train_latent_sampler(model, data, run.sampler, augment, trainer.config.seed))
    save_to_checkpoint(model, trainer.last_checkpoint, learned_sampler=settings)


def train(config: DictConfig | None = None, *, overrides: Sequence[str] = ()) -> Path:
    """Train a forecaster as ``mmf-rl train`` does: checkpoints, logs and the final model
    (``save_pretrained``) in the run directory.

    Args:
        config (DictConfig, optional): a composed train config, as ``mmf-rl train --cfg`` prints it
            (:func:`~mmf_rl.configuration.compose_config`, edited as you like). ``None``: compose
            ``configs/train.yaml`` with ``overrides``.

    Keyword Args:
        overrides (Sequence[str], optional): Hydra overrides, as on the command line
            (``group=option``, ``key=value``); only without ``config``.

    Returns:
        The run directory (resolved).

    Raises:
        ValueError: both ``config`` and ``overrides`` given.

    Examples:
        A tiny push recording, then 2 training steps of a small paper model on it:

        >>> import tempfile
        >>> from pathlib import Path
        >>> import mmf_rl
        >>> from mmf_rl.record import RecordConfig, record
        >>> tmp = Path(tempfile.mkdtemp())
        >>> root = record(RecordConfig(out=tmp / "push", episodes=6, steps=40, image_size=32))
        >>> small = ["data.image_size=[32,32]", "data.history=4", "data.horizon=3",
        ...          "model.d_model=16", "model.num_heads=2", "trainer.batch_size=8",
        ...          "trainer.progress_bar=false", "logger=csv", "num_workers=0"]
        >>> run_dir = mmf_rl.train(
        ...     overrides=[f"data.root={root}", "trainer.total_steps=2", f"run_dir={tmp / 'run'}", *small]
        ... )
        >>> (run_dir / "model" / "model.safetensors").exists()
        True

        The same with a composed config, edited before training:

        >>> from mmf_rl.configuration import compose_config
        >>> cfg = compose_config("train", [f"data.root={root}", f"run_dir={tmp / 'edited'}", *small])
        >>> cfg.trainer.total_steps = 2
        >>> mmf_rl.train(cfg).name
        'edited'
    """
    run = TrainRunConfig.from_config(config_or_overrides("train", config, overrides))
    device = resolve_device(run.device)
    rank, world_size = init_distributed(device)
    check_loss_settings_read(run)
    check_sampler_settings(int(run.model.get("learned_samples", 0)), run.sampler)
    run = prepare_run_dir(run, rank)
    data = open_windows(run, world_size)
    model, model_name, loss = build_model_and_loss(run, data, rank, device)
    trainer = make_trainer(run, model, model_name, loss, data, (rank, world_size), device)
    if run.resume:
        trainer.resume(run.run_dir / "checkpoints")
        if trainer.step < run.trainer.total_steps:
            # Scale factors fitted for the weights training is about to change (calibrate refits them).
            model.scale_calibration.reset()
        if rank == 0 and run.logger == "csv":
            truncate_csv_logs(run.run_dir / "logs", trainer.step)
    metrics = trainer.train()
    if rank == 0:
        save_trained_model(run, model, data, trainer, metrics, device)
    if world_size > 1:
        dist.destroy_process_group()
    return run.run_dir
