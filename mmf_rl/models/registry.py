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

    ``config_class`` has ``from_dict``/``to_dict`` and takes the data's ``modalities``, ``history``,
    ``horizon`` and ``target_dim``; ``loss`` names the loss terms the model trains with
    (``@register_loss_term``). Sets the class's ``model_name`` and ``config_class``, which its
    checkpoints and ``save_pretrained`` directories record.
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
    """The registry entry of model ``name``."""
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
) -> nn.Module:
    """``model_cfg`` is the model config group (its ``name`` picks the entry); the data fixes the rest.

    ``action_shape = (S, A)`` (the data config sets ``action``) builds an action-conditioned world
    model; only a model whose config has ``action_steps`` and ``action_dim`` (the paper's
    forecaster) has that option.
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
        if not {"action_steps", "action_dim"} <= _settings(entry.config_cls):
            raise ValueError(
                f"model {name!r} has no action input, but the data config sets `action` (a world model); "
                "use model=forecaster, or remove `action` from the data config"
            )
        fields.update(action_steps=action_shape[0], action_dim=action_shape[1])
    return entry.model_cls(entry.config_cls.from_dict(fields))


def trained_loss_terms(name: str, loss_cfg: LossConfig) -> tuple[str, ...]:
    """The loss terms model ``name`` trains with: the loss config's ``terms``, else the model's own."""
    return tuple(loss_cfg.terms) if loss_cfg.terms is not None else model_entry(name).loss_terms


def model_settings_from_group(model_cfg: Mapping) -> dict:
    """The settings the model config group ``model_cfg`` gives its model (its ``name``, else
    ``DEFAULT_MODEL``): its config class's defaults under the group's values, before the data fixes the
    rest and the model is built."""
    config_cls = model_entry(model_cfg.get("name", DEFAULT_MODEL)).config_cls
    fields = dataclasses.fields(config_cls)
    defaults = {field.name: field.default for field in fields if field.default is not dataclasses.MISSING}
    return {**defaults, **{key: value for key, value in model_cfg.items() if key != "name"}}


def loss_settings_read(model_cfg: Mapping, loss_cfg: LossConfig) -> frozenset[str]:
    """The settings of ``loss_cfg`` that the loss of the model config group ``model_cfg`` reads (e.g. not
    ``kl_warmup_steps`` with ``model=lf_lstm``, nor with ``loss.kl_weight=0``): without building it."""
    name = model_cfg.get("name", DEFAULT_MODEL)
    return settings_read(trained_loss_terms(name, loss_cfg), loss_cfg, model_settings_from_group(model_cfg))


def check_loss_settings(model_cfg: Mapping, loss_cfg: LossConfig, defaults: LossConfig | None = None) -> None:
    """Refuse a setting of ``loss_cfg`` changed from ``defaults`` (``LossConfig()``) that the loss terms
    the model config group ``model_cfg`` trains with do not read (a :class:`ConfigError` naming it):
    without building the model."""
    name = model_cfg.get("name", DEFAULT_MODEL)
    check_settings_read(
        trained_loss_terms(name, loss_cfg),
        loss_cfg,
        model_settings=model_settings_from_group(model_cfg),
        model_name=name,
        defaults=defaults,
    )


def build_loss(name: str, model: nn.Module, loss_cfg: LossConfig, *, check_unread: bool = True) -> nn.Module:
    """The losses model ``name`` trains with (or the loss config's ``terms``), weighted by the loss config;
    ``check_unread``: as :func:`~mmf_rl.objectives.build_loss_terms`."""
    return build_loss_terms(trained_loss_terms(name, loss_cfg), model, loss_cfg, check_unread=check_unread)


def saved_config(name: str, model: nn.Module) -> dict:
    """What a checkpoint stores to rebuild ``model``: its registry name and full config."""
    return {"name": name, **model.config.to_dict()}


def model_from_saved_config(saved: dict) -> nn.Module:
    """Rebuild a model from the ``model_config`` a checkpoint stores (see :func:`saved_config`)."""
    cfg = dict(saved)
    entry = model_entry(cfg.pop("name", DEFAULT_MODEL))
    return entry.model_cls(entry.config_cls.from_dict(cfg))


def _settings(config_cls: type) -> set[str]:
    return {f.name for f in dataclasses.fields(config_cls)}


def model_config_with_overrides(saved: dict, overrides: dict | None, where) -> dict:
    """A saved model config (:func:`saved_config`'s form) with ``overrides`` of its settings (e.g. an
    eval's ``eval_latent``), checked by the model's config class: a setting the model does not
    have, or a bad value, is a :class:`ConfigError` naming it and the model saved at ``where``."""
    if not overrides:
        return dict(saved)
    name = saved.get("name", DEFAULT_MODEL)
    entry = model_entry(name)
    given = ", ".join(f"{key}={value}" for key, value in overrides.items())
    unknown = [key for key in overrides if key not in _settings(entry.config_cls)]
    if unknown:
        having = sorted(n for n, e in MODELS.items() if set(unknown) <= _settings(e.config_cls))
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
