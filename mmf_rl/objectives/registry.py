"""Loss terms by name, so a model declares what it trains with and the loss config can pick others.

A term is a :class:`~mmf_rl.objectives.ForecasterLossBase` subclass with ``@register_loss_term(name)``;
its ``from_config(model, loss_cfg)`` builds it from the loss config group (``None``: the config
turns it off), its ``config_fields`` name the settings it reads and its ``unread_settings`` those it
reads only under a condition the config or the model leaves off. A new term is one class plus that
decorator.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from collections.abc import Iterable, Mapping, Sequence

from torch import nn

from mmf_rl.configuration import ConfigError
from mmf_rl.objectives.combined import CombinedLoss
from mmf_rl.objectives.common import ForecasterLossBase, model_settings_of
from mmf_rl.objectives.config import LossConfig
from mmf_rl.objectives.modality_dropout import with_modality_dropout

logger = logging.getLogger(__name__)

LOSS_TERMS: dict[str, type[ForecasterLossBase]] = {}
# Settings of the loss config that choose terms or act on every term (modality dropout, applied to the
# batch before all of them) rather than set one: no term reads them.
GLOBAL_LOSS_SETTINGS = frozenset({"terms", "modality_dropout", "modality_dropout_prob"})


def register_loss_term(name: str):
    """Class decorator: the :class:`ForecasterLossBase` subclass it decorates is the loss term ``name``.

    Args:
        name (str): the term's name, as ``loss.terms`` and a model's registry entry give it.

    Returns:
        The decorator; it returns the class unchanged and raises ``TypeError`` for a class that is not a
        :class:`ForecasterLossBase`, ``ValueError`` for a name already taken by another class.
    """

    def register(cls: type) -> type:
        if not (isinstance(cls, type) and issubclass(cls, ForecasterLossBase)):
            raise TypeError(
                f"@register_loss_term({name!r}) decorates a ForecasterLossBase subclass, found {cls!r}"
            )
        if LOSS_TERMS.get(name, cls) is not cls:
            raise ValueError(
                f"loss term {name!r} is already registered ({LOSS_TERMS[name].__qualname__}); pick another "
                "name"
            )
        LOSS_TERMS[name] = cls
        return cls

    return register


def loss_term(name: str) -> type[ForecasterLossBase]:
    """The class registered as loss term ``name``.

    Args:
        name (str): a registered term (``"nll"``, ``"elbo"``, ``"mis"``, ...).

    Returns:
        The term's class.

    Raises:
        ValueError: no term has that name (the message lists the registered ones).
    """
    if name not in LOSS_TERMS:
        raise ValueError(
            f"unknown loss term {name!r}; registered: {sorted(LOSS_TERMS)} "
            "(a new term is a ForecasterLossBase subclass with @register_loss_term(name))"
        )
    return LOSS_TERMS[name]


def terms_reading(setting: str, names: Iterable[str] | None = None) -> list[str]:
    """The loss terms whose ``from_config`` reads ``loss.<setting>``.

    Args:
        setting (str): a :class:`LossConfig` field.
        names (Iterable[str], optional): the terms to look at; ``None`` (default): every registered one.

    Returns:
        The names of the terms that list ``setting`` in their ``config_fields``.

    Examples:
        >>> from mmf_rl.objectives import terms_reading
        >>> terms_reading("kl_weight"), terms_reading("max_dropped")
        (['elbo'], ['mis'])
    """
    return [
        name
        for name in (sorted(LOSS_TERMS) if names is None else names)
        if setting in loss_term(name).config_fields
    ]


def settings_read(names: Iterable[str], loss_cfg: LossConfig, model_settings: Mapping) -> frozenset[str]:
    """The settings of ``loss_cfg`` that the terms ``names`` read for a model with ``model_settings``
    (:func:`~mmf_rl.objectives.common.model_settings_of`, or a model config group's settings): those
    they list in ``config_fields`` but what the config or the model leaves unread (``unread_settings``).

    Args:
        names (Iterable[str]): the terms.
        loss_cfg (LossConfig): the loss config.
        model_settings (Mapping): the model's settings.

    Returns:
        The names of the settings read.
    """
    read = set()
    for name in names:
        term = loss_term(name)
        read |= term.config_fields - term.unread_settings(loss_cfg, model_settings).keys()
    return frozenset(read)


def check_settings_read(
    names: Sequence[str],
    loss_cfg: LossConfig,
    *,
    model_settings: Mapping,
    model_name: str | None = None,
    defaults: LossConfig | None = None,
) -> None:
    """Refuse the settings of ``loss_cfg`` that differ from ``defaults`` (``LossConfig()``, the losses'
    own) and that none of the terms ``names`` reads for a model with ``model_settings``: training would
    silently ignore them.

    Args:
        names (Sequence[str]): the terms in use.
        loss_cfg (LossConfig): the loss config.

    Keyword Args:
        model_settings (Mapping): the model's settings (:func:`model_settings_of`).
        model_name (str, optional): the model the terms are for, named in the error.
        defaults (LossConfig, optional): what counts as unchanged; ``None``: ``LossConfig()``.

    Raises:
        ConfigError: a changed setting no term in use reads; it names each setting and either the terms
            that would read it and the terms in use, or the condition under which a term in use would
            read it (another setting, the model's prior).
    """
    defaults = LossConfig() if defaults is None else defaults
    changed = [
        field.name
        for field in dataclasses.fields(LossConfig)
        if field.name not in GLOBAL_LOSS_SETTINGS
        and getattr(loss_cfg, field.name) != getattr(defaults, field.name)
    ]
    read = settings_read(names, loss_cfg, model_settings)
    unread = [setting for setting in changed if setting not in read]
    no_reader = [setting for setting in unread if not terms_reading(setting, names)]
    problems = [_unread_message(no_reader, names, loss_cfg, model_name)] if no_reader else []
    conditional = [setting for setting in unread if setting not in no_reader]
    if conditional:
        problems.append(_conditional_message(conditional, names, loss_cfg, model_settings))
    if problems:
        raise ConfigError(". ".join(problems))


def _settings(settings: list[str], loss_cfg: LossConfig) -> str:
    return ", ".join(f"loss.{setting}={json.dumps(getattr(loss_cfg, setting))}" for setting in settings)


def _unread_message(unread: list[str], names: Sequence[str], loss_cfg: LossConfig, model_name) -> str:
    """``loss.a=1, loss.b=2 are read by the 'elbo' term and loss.c=3 by the 'mis' term, which ...``."""
    by_readers: dict[tuple[str, ...], list[str]] = {}
    for setting in unread:
        by_readers.setdefault(tuple(terms_reading(setting)), []).append(setting)
    readers = [
        _settings(settings, loss_cfg)
        + (" by " if i else " is read by " if len(settings) == 1 else " are read by ")
        + _term_list(terms)
        for i, (terms, settings) in enumerate(by_readers.items())
    ]
    if loss_cfg.terms is not None:
        trained, fix = f"loss.terms={list(names)} leaves out", "or add such a term to loss.terms"
    else:
        model = "the model" if model_name is None else f"model {model_name!r}"
        trained, fix = f"{model} does not train with (its terms: {list(names)})", "or pick loss.terms"
    them = "it" if len(unread) == 1 else "them"
    return f"{' and '.join(readers)}, which {trained}; remove {them} {fix}"


def _conditional_message(
    unread: list[str], names: Sequence[str], loss_cfg: LossConfig, model_settings: Mapping
) -> str:
    """``loss.a=1, loss.b=2 are read by the 'mis' term only with ...; set that or remove them``: settings
    that terms in use read only under a condition, grouped by the terms and their conditions."""
    conditions = {name: loss_term(name).unread_settings(loss_cfg, model_settings) for name in names}
    by_reason: dict[tuple[tuple[str, str], ...], list[str]] = {}
    for setting in unread:
        reason = tuple((name, conditions[name][setting]) for name in terms_reading(setting, names))
        by_reason.setdefault(reason, []).append(setting)
    return ". ".join(
        f"{_settings(settings, loss_cfg)} {'is' if len(settings) == 1 else 'are'} read by "
        + " and by ".join(f"the {name!r} term {condition}" for name, condition in reason)
        + f"; set that or remove {'it' if len(settings) == 1 else 'them'}"
        for reason, settings in by_reason.items()
    )


def _term_list(names: tuple[str, ...]) -> str:
    if not names:
        return "no registered loss term"
    quoted = " and ".join(repr(name) for name in names)
    return f"the {quoted} term" + ("s" if len(names) > 1 else "")


def build_loss_terms(
    names: Sequence[str], model: nn.Module, loss_cfg: LossConfig, *, check_unread: bool = True
) -> ForecasterLossBase:
    """The terms ``names`` for ``model``, weighted by ``loss_cfg``.

    A single term is returned as it is; several are a :class:`CombinedLoss` of those the config
    leaves on (one forward pass); with ``loss_cfg.modality_dropout``, wrapped in a
    :class:`~mmf_rl.objectives.ModalityDropout`. The structure decides the names of the loss's buffers in a
    checkpoint, so it depends on the names given, not on which terms the config turns off.

    Args:
        names (Sequence[str]): the registered terms (e.g. a model entry's ``("elbo", "mis")``).
        model (nn.Module): the model they train.
        loss_cfg (LossConfig): their settings.

    Keyword Args:
        check_unread (bool, optional): refuse a setting changed from ``LossConfig()``'s default that none
            of the terms reads (:func:`check_settings_read`; default). ``False`` skips that, for a caller
            that checked against other defaults (``mmf-rl train``: the loss config group's) or rebuilds
            the loss of a run as it was trained.

    Returns:
        The loss module.

    Raises:
        ValueError: no names, an unknown term, or a config that turns off every term.
        ConfigError: an unread setting (with ``check_unread``).

    Examples:
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import LossConfig, build_loss_terms
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> type(build_loss_terms(["elbo", "mis"], model, LossConfig())).__name__
        'CombinedLoss'
        >>> no_mis = LossConfig(missing_modality_weight=0)  # turns 'mis' off; the structure stays
        >>> type(build_loss_terms(["elbo", "mis"], model, no_mis).losses[0]).__name__
        'ELBOLoss'
        >>> build_loss_terms(["nll"], model, LossConfig(kl_weight=0.5))
        Traceback (most recent call last):
            ...
        mmf_rl.configuration.ConfigError: loss.kl_weight=0.5 is read by the 'elbo' term, which ...
    """
    if not names:
        raise ValueError(f"no loss terms given; expected names among {sorted(LOSS_TERMS)}")
    if check_unread:
        check_settings_read(
            names,
            loss_cfg,
            model_settings=model_settings_of(model),
            model_name=getattr(model, "model_name", None),
        )
    terms = {name: loss_term(name).from_config(model, loss_cfg) for name in names}
    off = [name for name, term in terms.items() if term is None]
    if off:
        logger.info("loss terms off in the loss config: %s", ", ".join(off))
    on = [term for term in terms.values() if term is not None]
    if not on:
        raise ValueError(f"the loss config turns off every loss term of {list(names)}; nothing to train")
    return with_modality_dropout(on[0] if len(names) == 1 else CombinedLoss(*on), loss_cfg)
