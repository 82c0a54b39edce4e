"""Models by name, so configs, checkpoints and benchmarks build any of them the same way.

A model registers itself with ``@register_model(name, config_class, loss=...)`` on its class: its
config class and the loss terms it trains with (names of ``mmf_rl.objectives.LOSS_TERMS``). Every
model reads the same batch contract (mmf_rl.keys) and writes ``("forecast", "loc"/"scale")``;
models with a latent also write ``("posterior", ...)``. This module imports no model: each model's
module imports it to register, and ``mmf_rl.models`` imports every model's module (and registers
the forecaster, whose package stays free of the registry).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from torch import nn

from mmf_rl.configuration import ConfigError
from mmf_rl.keys import ModalitySpec
from mmf_rl.objectives import LossConfig, build_loss_terms, check_settings_read, settings_read

DEFAULT_MODEL = "forecaster"  # the model of a config or checkpoint that names none


@dataclass(frozen=True)
class ModelEntry:
    model_cls: type  # names itself (``model_name``) and its config class (``config_class``)
    loss_terms: tuple[str, ...]  # what it trains with unless the loss config names other terms

    @property
    def config_cls(self) -> type:
        return self.model_cls.config_class


MODELS: dict[str, ModelEntry] = {}


def register_model(name: str, config_class: type, *, loss: Sequence[str]):
    """Class decorator: the model class it decorates is the model ``name`` (``model.name=...``).

    ``config_class`` has ``from_dict``/``to_dict`` (and may have ``from_saved_dict``, see
    :func:`config_from_saved`) and takes the data's ``modalities``, ``history``, ``horizon`` and
    ``target_dim``; ``loss`` names the loss terms the model trains with (``@register_loss_term``). Sets
    the class's ``model_name`` and ``config_class``, which its checkpoints and ``save_pretrained``
    directories record.

    Args:
        name (str): the model's name (``model.name=...``).
        config_class (type): its config dataclass.

    Keyword Args:
        loss (Sequence[str]): the loss terms it trains with (e.g. ``("elbo", "mis")``).

    Returns:
        The decorator; it returns the class itself and raises ``ValueError`` for a name another class
        took.

    Raises:
        TypeError: ``loss`` is a string or empty.
    """
    if isinstance(loss, str) or not loss:
        raise TypeError(
            f"@register_model({name!r}): loss is a non-empty sequence of loss term names, found {loss!r}"
        )

    def register(cls: type) -> type:
        if name in MODELS and MODELS[name].model_cls is not cls:
            raise ValueError(
                f"model {name!r} is already registered ({MODELS[name].model_cls.__qualname__}); pick "
                "another name"
            )
        cls.model_name, cls.config_class = name, config_class
        MODELS[name] = ModelEntry(cls, tuple(loss))
        return cls

    return register


def model_entry(name: str) -> ModelEntry:
    """The registry entry of model ``name``.

    Args:
        name (str): a registered model (``"forecaster"``, ``"lf_lstm"``, ``"mvae"``, ``"mult"``, ...).

    Returns:
        Its ``ModelEntry``: ``model_cls``, ``config_cls`` and ``loss_terms``.

    Raises:
        ValueError: no model has that name (the message lists the registered ones).
    """
    if name not in MODELS:
        raise ValueError(
            f"unknown model {name!r}; expected one of {sorted(MODELS)} "
            "(a new model registers with @register_model(name, config_class, loss=...) on its class)"
        )
    return MODELS[name]


def build_model(
    model_cfg: dict,
    modalities: list[ModalitySpec],
    history: int,
    horizon: int,
    target_dim: int,
    action_shape: tuple[int, int] | None = None,
    *,
    saved: bool = False,
) -> nn.Module:
    """Build a registered model from its config group's settings and the data's shapes.

    Args:
        model_cfg (dict): the model config group: ``name`` picks the entry (default ``"forecaster"``),
            the other keys are its config's settings.
        modalities (list[ModalitySpec]): the data's modalities (``WindowDataset.specs``).
        history (int): ``H``.
        horizon (int): ``T``.
        target_dim (int): ``D``.
        action_shape (tuple[int, int], optional): ``(S, A)`` when the data config sets ``action``: builds
            an action-conditioned world model; only a model whose config has ``action_steps`` and
            ``action_dim`` (the paper's forecaster) has that option.

    Keyword Args:
        saved (bool, optional): ``model_cfg`` is a saved run's model group (a resumed run's): a setting
            it lacks takes the value describing the model saved then (:func:`config_from_saved`), not
            today's default. Defaults to ``False`` (a new model: today's defaults).

    Returns:
        The model (in train mode).

    Raises:
        ValueError: an unknown model, a setting its config refuses, or actions for a model without
            an action input.

    Examples:
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import build_model
        >>> modalities = [ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))]
        >>> model = build_model({"name": "mult", "d_model": 16, "num_heads": 2}, modalities, 4, 5, 2)
        >>> type(model).__name__, model.config.horizon
        ('MulT', 5)
        >>> sizes = {"d_model": 16, "num_heads": 2}  # no name: the forecaster
        >>> world_model = build_model(sizes, modalities, 4, 5, 2, action_shape=(5, 4))
        >>> world_model.config.action_shape
        (5, 4)
    """
    cfg = dict(model_cfg)
    name = cfg.pop("name", DEFAULT_MODEL)
    entry = model_entry(name)
    fields = {
        **cfg,
        "modalities": modalities,
        "history": history,
        "horizon": horizon,
        "target_dim": target_dim,
    }
    if action_shape is not None:
        if not {"action_steps", "action_dim"} <= config_settings(entry.config_cls):
            raise ValueError(
                f"model {name!r} has no action input, but the data config sets `action` (a world model); "
                "use model=forecaster, or remove `action` from the data config"
            )
        fields.update(action_steps=action_shape[0], action_dim=action_shape[1])
    return entry.model_cls(
        config_from_saved(entry.config_cls, fields) if saved else entry.config_cls.from_dict(fields)
    )


def trained_loss_terms(name: str, loss_cfg: LossConfig) -> tuple[str, ...]:
    """The loss terms model ``name`` trains with: the loss config's ``terms``, else the model's own.

    Args:
        name (str): a registered model.
        loss_cfg (LossConfig): the loss config.

    Returns:
        The terms' names.
    """
    return tuple(loss_cfg.terms) if loss_cfg.terms is not None else model_entry(name).loss_terms


def model_settings_from_group(model_cfg: Mapping, *, saved: bool = False) -> dict:
    """The settings the model config group ``model_cfg`` gives its model (its ``name``, else
    ``DEFAULT_MODEL``): its config class's defaults under the group's values, before the data fixes the
    rest and the model is built.

    With ``saved=True`` the group is a saved run's: a setting it lacks that its config class's
    ``SAVED_BEFORE`` names takes that value (what :func:`config_from_saved` reads it as), not the
    default."""
    config_cls = model_entry(model_cfg.get("name", DEFAULT_MODEL)).config_cls
    fields = dataclasses.fields(config_cls)
    defaults = {field.name: field.default for field in fields if field.default is not dataclasses.MISSING}
    if saved:
        defaults |= getattr(config_cls, "SAVED_BEFORE", {})
    return {**defaults, **{key: value for key, value in model_cfg.items() if key != "name"}}


def loss_settings_read(model_cfg: Mapping, loss_cfg: LossConfig) -> frozenset[str]:
    """The settings of ``loss_cfg`` that the loss of the model config group ``model_cfg`` reads (e.g. not
    ``kl_warmup_steps`` with ``model=lf_lstm``, nor with ``loss.kl_weight=0``): without building it.

    Args:
        model_cfg (Mapping): the model config group (its ``name`` and settings).
        loss_cfg (LossConfig): the loss config.

    Returns:
        The names of the settings read.
    """
    name = model_cfg.get("name", DEFAULT_MODEL)
    return settings_read(trained_loss_terms(name, loss_cfg), loss_cfg, model_settings_from_group(model_cfg))


def check_loss_settings(model_cfg: Mapping, loss_cfg: LossConfig, defaults: LossConfig | None = None) -> None:
    """Refuse a setting of ``loss_cfg`` changed from ``defaults`` (``LossConfig()``) that the loss terms
    the model config group ``model_cfg`` trains with do not read: without building the model.

    Args:
        model_cfg (Mapping): the model config group (its ``name`` and settings).
        loss_cfg (LossConfig): the loss config.
        defaults (LossConfig, optional): what counts as unchanged; ``None``: ``LossConfig()``.

    Raises:
        ConfigError: such a setting, named with the terms that would read it.
    """
    name = model_cfg.get("name", DEFAULT_MODEL)
    check_settings_read(
        trained_loss_terms(name, loss_cfg),
        loss_cfg,
        model_settings=model_settings_from_group(model_cfg),
        model_name=name,
        defaults=defaults,
    )


def build_loss(name: str, model: nn.Module, loss_cfg: LossConfig, *, check_unread: bool = True) -> nn.Module:
    """The losses model ``name`` trains with (or the loss config's ``terms``), weighted by the loss config.

    Args:
        name (str): the model's registered name.
        model (nn.Module): the built model.
        loss_cfg (LossConfig): the loss config.

    Keyword Args:
        check_unread (bool, optional): as :func:`~mmf_rl.objectives.build_loss_terms`. Defaults to
            ``True``.

    Returns:
        The loss module (one term, or a :class:`~mmf_rl.objectives.CombinedLoss`).
    """
    return build_loss_terms(trained_loss_terms(name, loss_cfg), model, loss_cfg, check_unread=check_unread)


def saved_config(name: str, model: nn.Module) -> dict:
    """What a checkpoint stores to rebuild ``model``: its registry name and full config.

    Args:
        name (str): the model's registered name.
        model (nn.Module): the model.

    Returns:
        ``{"name": name, **model.config.to_dict()}``.
    """
    return {"name": name, **model.config.to_dict()}


def config_from_saved(config_cls: type, fields: dict):
    """The config of a saved model: ``config_cls.from_saved_dict(fields)`` when the class has it (a
    config whose defaults changed since a model could be saved without a setting: such a saved config
    describes the model of its time, e.g.
    :meth:`~mmf_rl.models.ForecasterConfig.from_saved_dict`), else ``from_dict``.

    Args:
        config_cls (type): the model's config class.
        fields (dict): the saved config's fields, without its ``name``.

    Returns:
        The config.

    Raises:
        ValueError: an unknown key or an invalid value.
    """
    return getattr(config_cls, "from_saved_dict", config_cls.from_dict)(fields)


def model_from_saved_config(saved: dict) -> nn.Module:
    """Rebuild a model from the ``model_config`` a checkpoint stores (see :func:`saved_config`).

    Args:
        saved (dict): the saved config (its ``name``, default ``"forecaster"``, and fields), read by
            :func:`config_from_saved`.

    Returns:
        The model, with fresh weights.
    """
    cfg = dict(saved)
    entry = model_entry(cfg.pop("name", DEFAULT_MODEL))
    return entry.model_cls(config_from_saved(entry.config_cls, cfg))


def config_settings(config_cls: type) -> set[str]:
    """The setting names of a model config class (its dataclass fields)."""
    return {f.name for f in dataclasses.fields(config_cls)}


def model_config_with_overrides(saved: dict, overrides: dict | None, where) -> dict:
    """A saved model config (:func:`saved_config`'s form) with ``overrides`` of its settings (e.g. an
    eval's ``eval_latent``), checked by the model's config class.

    Args:
        saved (dict): the saved model config.
        overrides (dict, optional): the settings to change; ``None`` or empty: none.
        where (str | Path): where the model was saved, named in the errors.

    Returns:
        A new saved config with the overrides.

    Raises:
        ConfigError: a setting the model does not have, or a bad value, naming it and the model.
    """
    if not overrides:
        return dict(saved)
    name = saved.get("name", DEFAULT_MODEL)
    entry = model_entry(name)
    given = ", ".join(f"{key}={value}" for key, value in overrides.items())
    unknown = [key for key in overrides if key not in config_settings(entry.config_cls)]
    if unknown:
        having = sorted(n for n, e in MODELS.items() if set(unknown) <= config_settings(e.config_cls))
        raise ConfigError(
            f"{given}: the {name!r} model of {where} has no setting {', '.join(unknown)}; remove it"
            + (f" (models that have it: {', '.join(having)})" if having else "")
        )
    config = {**saved, **overrides}
    try:
        config_from_saved(entry.config_cls, {key: value for key, value in config.items() if key != "name"})
    except ValueError as err:
        raise ConfigError(f"{given} for the {name!r} model of {where}: {err}") from None
    return config
