"""`mmf-rl train [overrides]`: a LeRobot dataset in, a trained missing-modality forecaster out.

    mmf-rl train data=so101 trainer.total_steps=500 run_dir=runs/so101
    mmf-rl train data=/path/to/mine.yaml run_dir=runs/mine     # a data config of your own (`mmf-rl inspect`)
    mmf-rl train --cfg data=so101 model=lf_lstm                # print the composed config, do not train
    torchrun --nproc_per_node=2 -m mmf_rl.cli train ...     # data parallel (gloo on CPU, NCCL on GPU)

Top to bottom: compose the config, set up devices and processes, open the window cache, build
the model and its losses, train with checkpoints, logs and validation, then save the final
weights. ``resume=true`` continues the run in ``run_dir`` exactly where its last checkpoint was;
``init_from=RUN_OR_CHECKPOINT`` fine-tunes: a new run starting from another run's (or a
``save_pretrained`` directory's) weights, with a new optimizer and schedule, at step 0, and the
normalisation statistics of this run's data. With ``calibrate=true`` (the default) the trained
model's forecast scale is then recalibrated per presence pattern on the val split (what
``mmf-rl calibrate`` does) and the last checkpoint re-saved with the factors. A model with a learned
sampler (``model.learned_samples=K``) has it trained first, for ``sampler.steps``, on the frozen
forecaster (:mod:`mmf_rl.trainers.latent_sampler`). The final model is
also written with ``save_pretrained`` to ``run_dir/model`` (weights, config, statistics, data
config, and the calibration's fit).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
import sys
import warnings
from datetime import timedelta
from pathlib import Path

import torch
import torch.distributed as dist
from omegaconf import OmegaConf

from mmf_rl.checkpoint import CheckpointError, list_checkpoints, load_checkpoint, remove_leftovers
from mmf_rl.configuration import (
    ConfigError,
    config_changes,
    load_config,
    parse_config_command,
    report_command_error,
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
from mmf_rl.models.registry import DEFAULT_MODEL
from mmf_rl.objectives import LossConfig, default_loss_config, resolve_observed_dropout
from mmf_rl.trainers.latent_sampler import SamplerConfig, check_sampler_settings, train_latent_sampler
from mmf_rl.trainers.trainer import Trainer, TrainerConfig, TrainingStopped, seed_everything

logger = logging.getLogger(__name__)

RUN_CONFIG = "config.yaml"
PRETRAINED_DIR = RUN_EXPORT_DIR  # run_dir/model: the final weights as save_pretrained writes them
EXAMPLES = [
    "mmf-rl train data=so101 trainer.total_steps=500 run_dir=runs/so101",
    "mmf-rl train data=/path/to/mine.yaml run_dir=runs/mine      # your own data config (mmf-rl inspect "
    "writes one)",
    "mmf-rl train --cfg data.root=/data/mine data.modalities='{cam: observation.images.top}' "
    "data.target=observation.state   # print the composed config only",
]
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


def trained_differently(run_dir: Path, cfg, ignore=frozenset()) -> dict[str, tuple]:
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


def check_resumable(run_dir: Path, cfg) -> None:
    saved_path = run_dir / RUN_CONFIG
    if not saved_path.is_file():
        raise CheckpointError(f"resume=true but {saved_path} does not exist: nothing to resume in {run_dir}")
    saved = OmegaConf.to_container(load_config(saved_path))
    added, changed = config_changes(saved, to_container(cfg), RESUMABLE_CHANGES)
    # Settings a newer mmf-rl added since the run started: the saved config cannot hold them, and
    # refusing them would make every run unresumable after an upgrade. They are taken as composed
    # now (their defaults, unless set on this command line) and named.
    if added:
        warnings.warn(
            f"resuming {run_dir}: its {saved_path.name} predates the settings "
            + ", ".join(f"{k}={v!r}" for k, v in added.items())
            + "; the resumed run uses these values",
            stacklevel=2,
        )
    if changed:
        details = ", ".join(f"{k}: {old!r} -> {new!r}" for k, (old, new) in list(changed.items())[:8])
        raise CheckpointError(
            f"resume=true with a config that differs from {saved_path} ({details}); resume with "
            "the same config, or train into a new run_dir"
        )


def check_name(name: str) -> None:
    """``name`` becomes a directory name (``run_dir: runs/${name}``): one path component, no traversal."""
    if any(sep in name for sep in (os.sep, os.altsep) if sep) or name in ("", ".", ".."):
        raise ConfigError(
            f"name={name!r} must be a plain name without path separators (it names the run "
            "directory runs/<name>); to train elsewhere set run_dir=PATH instead"
        )


def prepare_run_dir(cfg, rank: int) -> Path:
    """The run directory, resolved into ``cfg.run_dir``; on rank 0, cleaned of a killed save's
    leftovers, checked against the run it would resume or overwrite, and given the config."""
    # Relative paths and '..' are the user's choice; the saved config and the messages show where
    # they really lead.
    run_dir = Path(cfg.run_dir).resolve()
    cfg.run_dir = str(run_dir)
    if rank == 0:
        for leftover in remove_leftovers(run_dir / "checkpoints"):
            logger.info("removed %s: left by a run killed while saving or pruning a checkpoint", leftover)
        if cfg.resume:
            check_resumable(run_dir, cfg)
        elif list_checkpoints(run_dir / "checkpoints"):
            raise CheckpointError(
                f"{run_dir} already holds a trained run; pass resume=true to continue it, or "
                "choose another run_dir (nothing was overwritten)"
            )
        save_config(cfg, run_dir / RUN_CONFIG)
    return run_dir


def open_windows(cfg, data_cfg: DataConfig, world_size: int) -> WindowDataset:
    """The window cache of ``data_cfg``, built by one process per machine."""
    for name, modality in data_cfg.modalities.items():  # before the window cache is built
        if modality.encoder is not None:
            check_encoder(name, modality.encoder, modality.kind)
    # One process per machine builds the cache (or waits on the cache directory's lock for
    # another machine's build on a shared filesystem); the others open it after the barrier.
    builder = int(os.environ.get("LOCAL_RANK", "0")) == 0
    if builder:
        data = WindowDataset(data_cfg, num_workers=cfg.num_workers)
        logger.info("window cache %s: %s", "built" if data.built else "opened", data.cache_path)
    if world_size > 1:
        dist.barrier()
    if not builder:
        with warnings.catch_warnings():  # the builder already warned about absent modalities
            warnings.simplefilter("ignore")
            data = WindowDataset(data_cfg)
    return data


def build_model_and_loss(
    cfg, data: WindowDataset, trainer_cfg: TrainerConfig, loss_cfg: LossConfig, rank, device
):
    """The model on ``device`` (the same initial weights on every rank, or those of ``init_from``),
    its name and its loss module."""
    seed_everything(trainer_cfg.seed)  # same initial weights on every rank
    model_cfg = to_container(cfg.model)
    model = build_model(
        model_cfg,
        data.specs,
        data.config.history,
        data.config.horizon,
        data.target_dim,
        action_shape=data.action_shape,
    ).to(device)
    model_name = model_cfg.get("name", DEFAULT_MODEL)
    if cfg.get("init_from") is not None and not cfg.resume:  # resuming restores the run's own weights
        source = init_weights_from(model, cfg.init_from)
        if rank == 0:
            logger.info("fine-tuning from %s: weights copied, new optimizer, step 0", source)
    # The settings were checked by check_loss_settings_read (a new run) or are the run's own (resumed).
    absent = {name: outages["fraction"] for name, outages in data.observed_outages.items()}
    loss = build_loss(model_name, model, resolve_observed_dropout(loss_cfg, absent), check_unread=False)
    return model, model_name, loss


def check_loss_settings_read(cfg, loss_cfg: LossConfig) -> None:
    """A new run may not carry a loss setting that its model's loss terms do not read (e.g.
    ``loss.best_of_k_weight`` with ``model=lf_lstm``, ``loss.dropped_prior_weight`` without
    ``model.prior=learned``): training would silently ignore it. Compared with what the loss config group
    gives without asking (its KL warm-up is every model's, read by the ELBO's only), before the run
    directory and the window cache are made. A resumed run is not checked: it continues as it began, and
    one begun before this check may hold such a setting, which changed nothing in it."""
    if not cfg.resume:
        check_loss_settings(to_container(cfg.model), loss_cfg, default_loss_config())


def training_augmentation(cfg, data: WindowDataset, seed: int) -> TrainingAugmentation | None:
    """The run's augmentation of training batches (``augment`` group), ``None`` when it does nothing."""
    augment_cfg = AugmentConfig.from_dict(to_container(cfg.augment) if "augment" in cfg else None)
    if augment_cfg.enable or augment_cfg.rotation:
        return TrainingAugmentation(augment_cfg, data.specs, seed)
    return None


def make_trainer(cfg, model, model_name: str, loss, data: WindowDataset, trainer_cfg, run_dir, ranks, device):
    """The `Trainer` of the run: its train loader (augmented if configured), validation on the val
    split, checkpoints that carry the config and the normalisation statistics."""
    rank, world_size = ranks
    seed_everything(trainer_cfg.seed + rank)  # then each rank draws its own latents
    loader = data.loader(
        "train",
        trainer_cfg.batch_size,
        seed=trainer_cfg.seed,
        rank=rank,
        world_size=world_size,
        augment=training_augmentation(cfg, data, trainer_cfg.seed),
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
        run_dir=run_dir,
        logger=make_logger(cfg.logger, run_dir) if rank == 0 else None,
        evaluate=validate if len(data.split_windows["val"]) else None,
        checkpoint_meta={
            "config": to_container(cfg),
            "model_config": saved_config(model_name, model),
            "data_fingerprint": data.cache_path.name,
            "world_size": world_size,
        },
        checkpoint_tensors=data.normalizer.stats,
        rank=rank,
        world_size=world_size,
    )


def save_trained_model(cfg, model, data: WindowDataset, trainer: Trainer, metrics: dict, device) -> None:
    """The trained model with what it needs to forecast (statistics, data config, scale factors
    unless ``calibrate=false``), ready for from_pretrained / push_to_hub, in ``run_dir/model``."""
    run_dir = Path(cfg.run_dir)
    model.normalization_stats, model.data_config = data.normalizer.stats, data.config.to_dict()
    if getattr(model, "latent_sampler", None) is not None:
        train_sampler_once(cfg, model, data, trainer)
    if cfg.calibrate:
        logger.info("%s", calibrate_after_training(model, data, trainer.last_checkpoint, device))
    model.save_pretrained(run_dir / PRETRAINED_DIR)
    summary = ", ".join(f"{k}={v:.4g}" for k, v in metrics.items())
    logger.info(
        "trained %d steps -> %s%s",
        trainer.step,
        trainer.last_checkpoint,
        f" ({summary})" if summary else "",
    )


def sampler_config(cfg) -> SamplerConfig:
    return SamplerConfig.from_dict(to_container(cfg.sampler) if "sampler" in cfg else None)


def train_sampler_once(cfg, model, data: WindowDataset, trainer: Trainer) -> None:
    """Train the model's learned sampler after the forecaster and store it in the last checkpoint, unless
    that checkpoint already holds it trained with these settings (a resumed run that had finished)."""
    config = sampler_config(cfg)
    settings = dataclasses.asdict(config)
    if load_checkpoint(trainer.last_checkpoint).meta.get("learned_sampler") == settings:
        logger.info("learned sampler already trained in %s", trainer.last_checkpoint)
        return
    augment = training_augmentation(cfg, data, trainer.config.seed)
    logger.info("%s", train_latent_sampler(model, data, config, augment, trainer.config.seed))
    save_to_checkpoint(model, trainer.last_checkpoint, learned_sampler=settings)


def train(cfg) -> Path:
    check_name(str(cfg.name))
    device = resolve_device(cfg.device)
    rank, world_size = init_distributed(device)
    trainer_cfg = TrainerConfig.from_dict(to_container(cfg.trainer))
    loss_cfg = LossConfig.from_dict(to_container(cfg.loss))
    check_loss_settings_read(cfg, loss_cfg)
    check_sampler_settings(int(cfg.model.get("learned_samples", 0)), sampler_config(cfg))
    run_dir = prepare_run_dir(cfg, rank)
    data = open_windows(cfg, DataConfig.from_dict(to_container(cfg.data)), world_size)
    model, model_name, loss = build_model_and_loss(cfg, data, trainer_cfg, loss_cfg, rank, device)
    trainer = make_trainer(
        cfg, model, model_name, loss, data, trainer_cfg, run_dir, (rank, world_size), device
    )
    if cfg.resume:
        trainer.resume(run_dir / "checkpoints")
        if trainer.step < trainer_cfg.total_steps:
            # Scale factors fitted for the weights training is about to change (calibrate refits them).
            model.scale_calibration.reset()
        if rank == 0 and cfg.logger == "csv":
            truncate_csv_logs(run_dir / "logs", trainer.step)
    metrics = trainer.train()
    if rank == 0:
        save_trained_model(cfg, model, data, trainer, metrics, device)
    if world_size > 1:
        dist.destroy_process_group()
    return run_dir


def distributed_failure(error: RuntimeError, run_dir: Path) -> str:
    """One line for a rank whose training broke under DDP: usually a peer died or hung."""
    checkpoints = list_checkpoints(run_dir / "checkpoints")
    resume = (
        f"continue from {checkpoints[-1]} with resume=true"
        if checkpoints
        else "nothing was checkpointed yet; start again"
    )
    cause = " ".join(str(error).split())[:300]
    return (
        f"rank {os.environ.get('RANK', '?')} of {os.environ['WORLD_SIZE']} stopped ({type(error).__name__}: "
        f"{cause}); if another rank died or hung, torchrun's report names it; {resume}"
    )


def main(argv: list[str]) -> int:
    command = parse_config_command(
        argv,
        "train",
        "mmf-rl train",
        "Train a missing-modality forecaster on a LeRobot "
        "dataset (configs/train.yaml composed with your overrides).",
        EXAMPLES,
    )
    try:
        cfg = command.compose("train")
        if command.print_config:
            print(OmegaConf.to_yaml(cfg), end="")
            return 0
        run_dir = Path(cfg.run_dir).resolve()
        train(cfg)
    except (ConfigError, CheckpointError, TrainingStopped, OSError, ValueError, KeyError) as err:
        return report_command_error("mmf-rl train", err)
    except RuntimeError as err:
        # Under DDP a dead or hung peer surfaces as a RuntimeError from a collective (gloo's
        # "Connection reset by peer", a timeout after MMF_RL_DIST_TIMEOUT seconds): say so in one
        # line instead of one traceback per surviving rank.
        if int(os.environ.get("WORLD_SIZE", "1")) == 1 or os.environ.get("MMF_RL_DEBUG"):
            raise
        print(f"mmf-rl train: error: {distributed_failure(err, run_dir)}", file=sys.stderr)
        return 1
    return 0
