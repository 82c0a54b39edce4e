"""Models by name, so configs, checkpoints and benchmarks build any of them the same way.

An entry gives the model's config class, its module class, and the losses it trains with. Every
model reads the same batch contract (mmf_rl.keys) and writes ``("forecast", "loc"/"scale")``;
models with a latent also write ``("posterior", ...)``. Baselines register here beside the
paper's forecaster.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from huggingface_hub.constants import CONFIG_NAME
from torch import nn

from mmf_rl.checkpoint import (
    LAST_POINTER,
    META_FILE,
    CheckpointError,
    load_checkpoint,
    load_model_state,
    read_meta,
    resolve_checkpoint,
)
from mmf_rl.configuration import ConfigError
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.baselines import MVAE, LateFusionLSTM, MulT
from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster
from mmf_rl.models.hub import DATA_CONFIG_FILE, NORMALIZATION_FILE, check_state_dict, read_pretrained_config
from mmf_rl.objectives import CombinedLoss, ELBOLoss, GaussianNLLLoss, LossConfig, MissingModalityLoss


@dataclass(frozen=True)
class ModelEntry:
    model_cls: type  # names itself (``model_name``) and its config class (``config_class``)
    make_loss: Callable[[nn.Module, LossConfig], nn.Module]

    @property
    def config_cls(self) -> type:
        return self.model_cls.config_class


def forecaster_loss(model: MultimodalForecaster, loss_cfg: LossConfig) -> CombinedLoss:
    """ELBO, plus the missing-modality loss unless its weight is 0 (the paper's ablation)."""
    losses = [
        ELBOLoss(
            model,
            kl_weight=loss_cfg.kl_weight,
            kl_warmup_steps=loss_cfg.kl_warmup_steps,
            gsnn_weight=loss_cfg.gsnn_weight,
        )
    ]
    if loss_cfg.missing_modality_weight > 0:
        losses.append(
            MissingModalityLoss(
                model,
                weight=loss_cfg.missing_modality_weight,
                detach_teacher=loss_cfg.detach_teacher,
                max_dropped=loss_cfg.max_dropped,
                dropped_nll_weight=loss_cfg.dropped_nll_weight,
                prior_weight=loss_cfg.dropped_prior_weight,
            )
        )
    return CombinedLoss(*losses)


def nll_loss(model: nn.Module, loss_cfg: LossConfig) -> GaussianNLLLoss:
    """Deterministic baselines: the Gaussian NLL of the future (the loss config has no term for them)."""
    return GaussianNLLLoss(model)


def mvae_loss(model: MVAE, loss_cfg: LossConfig) -> ELBOLoss:
    """The MVAE's ELBO with the loss config's KL weight and warm-up; it has no missing-modality term."""
    if loss_cfg.gsnn_weight > 0:
        raise ValueError(
            "loss.gsnn_weight > 0 needs a model that decodes from its prior in training "
            "(model=forecaster); the MVAE baseline does not: set loss.gsnn_weight=0"
        )
    return ELBOLoss(model, kl_weight=loss_cfg.kl_weight, kl_warmup_steps=loss_cfg.kl_warmup_steps)


MODELS: dict[str, ModelEntry] = {
    entry.model_cls.model_name: entry
    for entry in (
        ModelEntry(MultimodalForecaster, forecaster_loss),
        ModelEntry(LateFusionLSTM, nll_loss),
        ModelEntry(MVAE, mvae_loss),
        ModelEntry(MulT, nll_loss),
    )
}


def _entry(name: str) -> ModelEntry:
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; expected one of {sorted(MODELS)}")
    return MODELS[name]


def build_model(
    model_cfg: dict,
    modalities: list[ModalitySpec],
    history: int,
    horizon: int,
    target_dim: int,
    action_shape: tuple[int, int] | None = None,
) -> nn.Module:
    """``model_cfg`` is the model config group (its ``name`` picks the entry); the data fixes the rest.

    ``action_shape = (S, A)`` (the data config sets ``action``) builds an action-conditioned world
    model; only the paper's forecaster has that option.
    """
    cfg = dict(model_cfg)
    name = cfg.pop("name", "forecaster")
    entry = _entry(name)
    fields = {
        **cfg,
        "modalities": modalities,
        "history": history,
        "horizon": horizon,
        "target_dim": target_dim,
    }
    if action_shape is not None:
        if entry.config_cls is not ForecasterConfig:
            raise ValueError(
                f"model {name!r} has no action input, but the data config sets `action` (a world model); "
                "use model=forecaster, or remove `action` from the data config"
            )
        fields.update(action_steps=action_shape[0], action_dim=action_shape[1])
    return entry.model_cls(entry.config_cls.from_dict(fields))


def model_from_saved_config(saved: dict) -> nn.Module:
    """Rebuild a model from the ``model_config`` a checkpoint stores (see :func:`saved_config`)."""
    cfg = dict(saved)
    entry = _entry(cfg.pop("name", "forecaster"))
    return entry.model_cls(entry.config_cls.from_dict(cfg))


def model_config_with_overrides(saved: dict, overrides: dict | None, where) -> dict:
    """A saved model config (:func:`saved_config`'s form) with ``overrides`` of its settings (e.g. an
    eval's ``eval_latent``), checked by the model's config class: a setting the model does not
    have, or a bad value, is a :class:`ConfigError` naming it and the model saved at ``where``."""
    if not overrides:
        return dict(saved)
    name = saved.get("name", "forecaster")
    entry = _entry(name)

    def settings(config_cls) -> set[str]:
        return {f.name for f in dataclasses.fields(config_cls)}

    given = ", ".join(f"{key}={value}" for key, value in overrides.items())
    unknown = [key for key in overrides if key not in settings(entry.config_cls)]
    if unknown:
        having = sorted(n for n, e in MODELS.items() if set(unknown) <= settings(e.config_cls))
        raise ConfigError(
            f"{given}: the {name!r} model of {where} has no setting {', '.join(unknown)}; remove it"
            + (f" (models that have it: {', '.join(having)})" if having else "")
        )
    config = {**saved, **overrides}
    try:
        entry.config_cls.from_dict({key: value for key, value in config.items() if key != "name"})
    except ValueError as err:
        raise ConfigError(f"{given} for the {name!r} model of {where}: {err}") from None
    return config


def from_pretrained(
    model_id: str | os.PathLike, *, config_overrides: dict | None = None, **kwargs
) -> nn.Module:
    """Any registered model saved by ``save_pretrained``: a local directory or a hub repository id.

    ``config_overrides`` change settings of the saved config before the model is built (see
    :func:`model_config_with_overrides`); ``kwargs`` go to the class's ``from_pretrained``."""
    saved = read_pretrained_config(str(model_id), **kwargs)
    config = model_config_with_overrides(saved, config_overrides, model_id)
    entry = _entry(config.get("name", "forecaster"))
    # An explicit `config` replaces the mixin's reading of config.json (huggingface_hub's ModelHubMixin).
    return entry.model_cls.from_pretrained(str(model_id), config=config, **kwargs)


RUN_EXPORT_DIR = "model"  # RUN_DIR/model: a run's final weights as save_pretrained writes them

TRAINED_MODEL_KINDS = (
    "a run directory, its checkpoints/, one checkpoint (meta.json) or a directory written by save_pretrained "
    f"({CONFIG_NAME}, model.safetensors, {NORMALIZATION_FILE}, {DATA_CONFIG_FILE})"
)


@dataclass(frozen=True)
class TrainedModelSource:
    """What :func:`load_trained_model` reads: a checkpoint of a ``mmf-rl train`` run, or a directory
    written by ``save_pretrained`` (an export or a hub download: it records no training step)."""

    path: Path  # the checkpoint directory (step_*), or the save_pretrained directory
    kind: str  # "checkpoint" | "save_pretrained"
    step: int | None  # the checkpoint's training step; None for a save_pretrained directory


def _trained_location(path: Path) -> Path:
    """A run directory -> its ``checkpoints/``; anything else as given."""
    return path / "checkpoints" if (path / "checkpoints").is_dir() else path


def locate_trained_model(path) -> TrainedModelSource:
    """Where the trained model ``path`` names is (see :data:`TRAINED_MODEL_KINDS`), without loading it;
    anything else is a :class:`CheckpointError` saying what was found and what is expected."""
    given = Path(path)
    location = _trained_location(given)
    if (location / CONFIG_NAME).is_file() and not (location / META_FILE).is_file():
        return TrainedModelSource(location, "save_pretrained", None)
    if not given.exists():
        raise CheckpointError(f"{given} does not exist; expected {TRAINED_MODEL_KINDS}")
    if not location.is_dir():
        raise CheckpointError(f"{location} is a file, not a trained model; expected {TRAINED_MODEL_KINDS}")
    if not any((location / name).is_file() for name in (META_FILE, LAST_POINTER)):
        found = sorted(p.name + ("/" if p.is_dir() else "") for p in location.iterdir())
        holds = ", ".join(found[:5]) + (" ..." if len(found) > 5 else "") if found else "nothing"
        raise CheckpointError(
            f"{location} is not a trained model (it holds {holds}); expected {TRAINED_MODEL_KINDS}"
        )
    checkpoint = resolve_checkpoint(location)
    return TrainedModelSource(checkpoint, "checkpoint", int(read_meta(checkpoint)["step"]))


def load_trained_model(
    path, map_location="cpu", config_overrides: dict | None = None
) -> tuple[nn.Module, dict, dict]:
    """A trained model with its weights in eval mode, its normalisation stats and its data config.

    ``path``: a run directory, its ``checkpoints/``, one checkpoint, or a directory written by
    ``save_pretrained`` (:func:`locate_trained_model`). ``config_overrides`` change settings of the
    saved model config before the model is built, either way (:func:`model_config_with_overrides`;
    e.g. ``{"eval_latent": "predictive"}``). The model carries the stats and data config too
    (``normalization_stats``, ``data_config``), so ``model.save_pretrained(dir)`` exports all it needs,
    and ``calibration``: how its scale factors were fitted (``mmf-rl calibrate``; ``None`` if never)."""
    source = locate_trained_model(path)
    if source.kind == "save_pretrained":
        absent = [f for f in (NORMALIZATION_FILE, DATA_CONFIG_FILE) if not (source.path / f).is_file()]
        if absent:
            raise CheckpointError(
                f"{source.path} holds a saved model without {' and '.join(absent)} (its normalisation "
                "statistics and data config); save it from a trained run "
                "(load_trained_model(run).save_pretrained(dir))"
            )
        model = from_pretrained(source.path, config_overrides=config_overrides, map_location=map_location)
        return model, model.normalization_stats, model.data_config
    checkpoint = load_checkpoint(source.path, with_trainer_state=False)
    data_config = checkpoint.meta.get("config", {}).get("data")
    if "model_config" not in checkpoint.meta or not data_config:
        raise CheckpointError(
            f"{checkpoint.path}/{META_FILE} lacks the model config or the run config ('model_config', "
            "'config': {'data': ...}); it was not written by `mmf-rl train` (or save_checkpoint(meta="
            "{'model_config': saved_config(...), 'config': {'data': data_config.to_dict()}}))"
        )
    model = model_from_saved_config(
        model_config_with_overrides(checkpoint.meta["model_config"], config_overrides, checkpoint.path)
    )
    load_model_state(model, checkpoint)
    model.normalization_stats, model.data_config = checkpoint.tensors, data_config
    model.calibration = checkpoint.meta.get("calibration")
    return model.to(map_location).eval(), checkpoint.tensors, data_config


def init_weights_from(model: nn.Module, source_path) -> Path:
    """Fine-tuning: copy the weights of a trained model (``init_from``) into ``model``, built for this run.

    The source may be anything :func:`load_trained_model` reads. A different model type, a
    modality missing on either side or of another kind or shape, or a parameter of another shape
    is an error naming it (this run's value first, then the source's). The source's scale factors
    (``mmf-rl calibrate``) are not copied. Returns the source's path.
    """
    location = _trained_location(Path(source_path))
    source, _, _ = load_trained_model(location)
    here, there = model.model_name, source.model_name
    if here != there:
        raise CheckpointError(
            f"init_from={source_path} holds a {there!r} model, but this run builds {here!r}; "
            f"train model={there} or start from a {here!r} run"
        )
    mine = {s.name: (s.kind, tuple(s.shape)) for s in model.config.modalities}
    theirs = {s.name: (s.kind, tuple(s.shape)) for s in source.config.modalities}
    problems = [
        f"modality {n!r}: this run has {mine.get(n, 'none')}, {source_path} has {theirs.get(n, 'none')}"
        for n in sorted(set(mine) | set(theirs))
        if mine.get(n) != theirs.get(n)
    ]
    if problems:
        raise CheckpointError(
            "init_from: the modalities differ (" + "; ".join(problems) + "); map the same "
            "modality names to features of the same kind and shape (images: data.image_size)"
        )
    differing = sorted(
        k
        for k, v in model.config.to_dict().items()
        if k != "modalities" and source.config.to_dict().get(k) != v
    )
    try:
        check_state_dict(model, source.state_dict(), f"init_from={source_path}")
    except CheckpointError as error:
        hint = ", ".join(
            f"model.{k}: this run {getattr(model.config, k)!r}, source {getattr(source.config, k)!r}"
            for k in differing
        )
        raise CheckpointError(f"{error}{'; the configs differ in ' + hint if hint else ''}") from None
    model.load_state_dict(source.state_dict())
    # The source's scale factors were fitted for its weights, not for the ones fine-tuning makes.
    model.scale_calibration.reset()
    return location


def saved_config(name: str, model: nn.Module) -> dict:
    """What a checkpoint stores to rebuild ``model``: its registry name and full config."""
    return {"name": name, **model.config.to_dict()}


def build_loss(name: str, model: nn.Module, loss_cfg: LossConfig) -> nn.Module:
    """The losses model ``name`` trains with, weighted by the loss config group."""
    return _entry(name).make_loss(model, loss_cfg)
