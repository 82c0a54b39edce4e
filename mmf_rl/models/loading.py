"""Trained models from disk or the hub: a run's checkpoints, or a directory written by ``save_pretrained``."""

from __future__ import annotations

import os
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
from mmf_rl.models.hub import DATA_CONFIG_FILE, NORMALIZATION_FILE, read_pretrained_config
from mmf_rl.models.registry import (
    DEFAULT_MODEL,
    model_config_with_overrides,
    model_entry,
    model_from_saved_config,
)


def from_pretrained(
    model_id: str | os.PathLike, *, config_overrides: dict | None = None, **kwargs
) -> nn.Module:
    """Any registered model saved by ``save_pretrained``: a local directory or a hub repository id.

    Args:
        model_id (str | os.PathLike): the directory or the hub repository id.

    Keyword Args:
        config_overrides (dict, optional): settings of the saved config changed before the model is
            built (see :func:`model_config_with_overrides`).
        **kwargs: passed to the class's ``from_pretrained`` (``map_location``, ``revision``, ...).

    Returns:
        The model in eval mode, with ``normalization_stats``, ``data_config`` and ``calibration`` as
        saved (``None`` where not).

    Examples:
        >>> import tempfile
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster, from_pretrained
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,))], d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> directory = tempfile.mkdtemp()
        >>> model.save_pretrained(directory)
        >>> loaded = from_pretrained(directory, config_overrides={"eval_latent": "predictive"})
        >>> type(loaded).__name__, loaded.config.eval_latent, loaded.training
        ('MultimodalForecaster', 'predictive', False)
        >>> import shutil
        >>> shutil.rmtree(directory)
    """
    saved = read_pretrained_config(str(model_id), **kwargs)
    config = model_config_with_overrides(saved, config_overrides, model_id)
    entry = model_entry(config.get("name", DEFAULT_MODEL))
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
    written by ``save_pretrained`` (an export or a hub download: it records no training step).

    Args:
        path (Path): the checkpoint directory (``step_*``), or the ``save_pretrained`` directory.
        kind (str): ``"checkpoint"`` or ``"save_pretrained"``.
        step (int | None): the checkpoint's training step; ``None`` for a ``save_pretrained`` directory.
    """

    path: Path
    kind: str
    step: int | None


def trained_location(path: Path) -> Path:
    """A run directory -> its ``checkpoints/``; anything else as given."""
    return path / "checkpoints" if (path / "checkpoints").is_dir() else path


def locate_trained_model(path) -> TrainedModelSource:
    """Where the trained model ``path`` names is, without loading it.

    Args:
        path (str | Path): a run directory, its ``checkpoints/``, one checkpoint or a directory written
            by ``save_pretrained`` (:data:`TRAINED_MODEL_KINDS`).

    Returns:
        The checkpoint (the run's last one for a run) or the ``save_pretrained`` directory.

    Raises:
        CheckpointError: ``path`` is none of these; the message says what was found and what is
            expected.
    """
    given = Path(path)
    location = trained_location(given)
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
    and ``calibration``: how its scale factors were fitted (``mmf-rl calibrate``; ``None`` if never).

    Args:
        path (str | Path): what :func:`locate_trained_model` accepts.
        map_location (str | torch.device, optional): the device the model is moved to. Defaults to
            ``"cpu"``.
        config_overrides (dict, optional): settings of the saved model config to change.

    Returns:
        ``(model, stats, data_config)``: the model in eval mode, the normalisation statistics
        (``Normalizer.stats``' form) and the data config as a dict.

    Raises:
        CheckpointError: ``path`` is not a trained model, or lacks the statistics, the data config or
            the model config (the message says which).
        ConfigError: a bad override.
    """
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
