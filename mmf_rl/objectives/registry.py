"""Loss terms by name, so a model declares what it trains with and the loss config can pick others.

A term is a :class:`~mmf_rl.objectives.ForecasterLossBase` subclass with ``@register_loss_term(name)``;
its ``from_config(model, loss_cfg)`` builds it from the loss config group (``None``: the config
turns it off) and its ``config_fields`` name the settings it reads. A new term is one class plus that
decorator.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence

from torch import nn

from mmf_rl.objectives.combined import CombinedLoss
from mmf_rl.objectives.common import ForecasterLossBase
from mmf_rl.objectives.config import LossConfig

logger = logging.getLogger(__name__)

LOSS_TERMS: dict[str, type[ForecasterLossBase]] = {}


def register_loss_term(name: str):
    """Class decorator: the :class:`ForecasterLossBase` subclass it decorates is the loss term ``name``."""

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
    """The class registered as loss term ``name``."""
    if name not in LOSS_TERMS:
        raise ValueError(
            f"unknown loss term {name!r}; registered: {sorted(LOSS_TERMS)} "
            "(a new term is a ForecasterLossBase subclass with @register_loss_term(name))"
        )
    return LOSS_TERMS[name]


def terms_reading(setting: str, names: Iterable[str] | None = None) -> list[str]:
    """The loss terms among ``names`` (default: every registered one) whose ``from_config`` reads
    ``loss.<setting>``."""
    return [
        name
        for name in (sorted(LOSS_TERMS) if names is None else names)
        if setting in loss_term(name).config_fields
    ]


def build_loss_terms(names: Sequence[str], model: nn.Module, loss_cfg: LossConfig) -> ForecasterLossBase:
    """The terms ``names`` for ``model``, weighted by ``loss_cfg``.

    A single term is returned as it is; several are a :class:`CombinedLoss` of those the config
    leaves on (one forward pass). The structure decides the names of the loss's buffers in a
    checkpoint, so it depends on the names given, not on which terms the config turns off.
    """
    if not names:
        raise ValueError(f"no loss terms given; expected names among {sorted(LOSS_TERMS)}")
    terms = {name: loss_term(name).from_config(model, loss_cfg) for name in names}
    off = [name for name, term in terms.items() if term is None]
    if off:
        logger.info("loss terms off in the loss config: %s", ", ".join(off))
    on = [term for term in terms.values() if term is not None]
    if not on:
        raise ValueError(f"the loss config turns off every loss term of {list(names)}; nothing to train")
    if len(names) == 1:
        return on[0]
    return CombinedLoss(*on)
