"""Closed-form Gaussian terms and the base class shared by the forecaster's losses."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.objectives import LossModule

_LOG_2PI = math.log(2 * math.pi)


def gaussian_nll(value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Elementwise ``-log N(value; loc, scale²)``.

    Args:
        value (torch.Tensor): the observed values.
        loc (torch.Tensor): the Gaussian's mean (broadcast with ``value``).
        scale (torch.Tensor): its standard deviation, ``> 0``.

    Returns:
        The negative log-density of each element.

    Examples:
        >>> import torch
        >>> from mmf_rl.objectives import gaussian_nll
        >>> gaussian_nll(torch.tensor([0.0, 1.0]), torch.zeros(2), torch.ones(2))  # 0.5 log 2π, + 0.5
        tensor([0.9189, 1.4189])
    """
    return 0.5 * (((value - loc) / scale) ** 2 + _LOG_2PI) + scale.log()


def gaussian_kl(
    loc_p: torch.Tensor, scale_p: torch.Tensor, loc_q: torch.Tensor, scale_q: torch.Tensor
) -> torch.Tensor:
    """Elementwise ``KL(N(loc_p, scale_p²) || N(loc_q, scale_q²))``.

    Args:
        loc_p (torch.Tensor): the mean of ``p``.
        scale_p (torch.Tensor): the standard deviation of ``p``, ``> 0``.
        loc_q (torch.Tensor): the mean of ``q``.
        scale_q (torch.Tensor): the standard deviation of ``q``, ``> 0``.

    Returns:
        The KL divergence of each element (sum over the last dim for a diagonal Gaussian).
    """
    var_ratio = (scale_p / scale_q) ** 2
    return 0.5 * (var_ratio + ((loc_p - loc_q) / scale_q) ** 2 - 1 - var_ratio.log())


def gaussian_kl_to_standard(loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Elementwise ``KL(N(loc, scale²) || N(0, 1))``.

    Args:
        loc (torch.Tensor): the mean.
        scale (torch.Tensor): the standard deviation, ``> 0``.

    Returns:
        The KL divergence of each element.
    """
    return 0.5 * (scale**2 + loc**2 - 1) - scale.log()


def best_of_k_mse(target: torch.Tensor, samples: torch.Tensor) -> torch.Tensor:
    """``[B]``: the mean squared error over ``T × D`` of the closest of ``K`` forecasts ``samples``
    ``[B, K, T, D]`` to ``target`` ``[B, T, D]``; the min passes the gradient to that forecast only."""
    return (samples - target.unsqueeze(1)).square().flatten(2).mean(-1).amin(1)


def model_settings_of(model) -> dict:
    """A built model's settings by name: what a loss term's reads may depend on
    (:meth:`ForecasterLossBase.unread_settings`).

    Args:
        model (nn.Module): a built model.

    Returns:
        The fields of its dataclass ``config``, ``{name: value}``; empty for a module without one.
    """
    config = getattr(model, "config", None)
    if not dataclasses.is_dataclass(config):
        return {}
    return {field.name: getattr(config, field.name) for field in dataclasses.fields(config)}


def has_learned_prior(model_settings: Mapping) -> bool:
    """Whether a model with these settings has a learned prior ``p(z|X)`` (``model.prior=learned``);
    any other has ``N(0, I)`` or no latent, neither of which depends on the present modalities."""
    return model_settings.get("prior") == "learned"


def reduce_batch(per_sample: torch.Tensor, reduction: str) -> torch.Tensor:
    if reduction == "mean":
        return per_sample.mean()
    if reduction == "sum":
        return per_sample.sum()
    return per_sample


class ForecasterLossBase(LossModule):
    """A loss over one forecaster's outputs.

    ``loss(td)`` runs the forecaster on a shallow copy of ``td`` and computes the loss, so the
    caller's batch is never modified and never carries stale outputs. To run several losses on
    one forward pass, use :class:`~mmf_rl.objectives.CombinedLoss`, which calls each loss's
    :meth:`prepare` (inputs the pass needs), the forecaster once, then each
    :meth:`loss_from_outputs`.

    Keys follow torchrl: each loss's ``_AcceptedKeys`` dataclass (``default_keys``) names what it
    reads, ``tensor_keys`` holds this instance's names and ``set_keys`` renames them. Keys that
    depend on the forecaster (its modalities' presence masks) are resolved from it when the loss
    is built (:meth:`default_tensor_keys`). ``in_keys`` lists what ``forward`` reads: the loss's
    own keys, then the forecaster's ``in_keys`` (observations, presence masks...), as torchrl's
    losses list their networks' inputs.

    ``config_fields`` names the :class:`~mmf_rl.objectives.LossConfig` fields :meth:`from_config`
    reads: a registered term lists every one it reads, so that a setting none of a model's terms reads
    is refused (``build_loss_terms``) rather than silently ignored. A term that reads some of them only
    under a condition (another setting, the model's prior) says so in :meth:`unread_settings`.

    Args:
        forecaster (nn.Module): the model the loss runs.
        reduction (str, optional): ``"mean"`` (default) | ``"sum"`` | ``"none"`` over the batch.

    Raises:
        ValueError: an unknown ``reduction``.
    """

    REDUCTIONS = ("mean", "sum", "none")
    config_fields: frozenset[str] = frozenset()

    def __init__(self, forecaster, reduction: str = "mean"):
        super().__init__()
        if reduction not in self.REDUCTIONS:
            raise ValueError(f"reduction must be one of {self.REDUCTIONS}, found {reduction!r}")
        self.forecaster = forecaster
        self.reduction = reduction
        self._tensor_keys = self.default_tensor_keys()

    @property
    def functional(self) -> bool:
        # The forecaster is used as a plain stateful module: no target networks, no vmap.
        return False

    def default_tensor_keys(self):
        """This loss's default keys for its forecaster (what ``set_keys(name=None)`` restores)."""
        return self._AcceptedKeys()

    def set_keys(self, **kwargs) -> None:
        # torchrl 0.13.3 restores a key set to None with `default_keys().key`, an AttributeError;
        # pass it the default itself.
        defaults = self.default_tensor_keys()
        super().set_keys(**{k: getattr(defaults, k, None) if v is None else v for k, v in kwargs.items()})

    @classmethod
    def from_config(cls, forecaster, loss_cfg) -> ForecasterLossBase | None:
        """This loss for ``forecaster`` as the loss config group sets it.

        By default the loss's own defaults: a loss with settings in the loss config overrides this and
        lists them in ``config_fields``.

        Args:
            forecaster (nn.Module): the model.
            loss_cfg (LossConfig): the loss config.

        Returns:
            The loss, or ``None`` when the config turns it off.
        """
        return cls(forecaster)

    @classmethod
    def unread_settings(cls, loss_cfg, model_settings: Mapping) -> dict[str, str]:
        """The settings of ``config_fields`` that change nothing this term computes under ``loss_cfg`` for
        a model with ``model_settings`` (:func:`model_settings_of`), each with the condition under which
        it would, e.g. ``"only with loss.best_of_k_weight > 0 (found 0.0)"``. None by default: a term whose
        reads are conditional overrides this, so that such a setting is refused, not silently ignored.

        Args:
            loss_cfg (LossConfig): the loss config.
            model_settings (Mapping): the model's settings (:func:`model_settings_of`).

        Returns:
            ``{setting: condition}``.
        """
        return {}

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        """No value estimator: nothing to forward (required by ``set_keys``)."""

    def _loss_in_keys(self) -> list:
        """The keys of ``tensor_keys`` this loss reads."""
        raise NotImplementedError

    @property
    def in_keys(self) -> list:
        own = self._loss_in_keys()
        return own + [k for k in getattr(self.forecaster, "in_keys", []) if k not in own]

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        """Add the inputs this loss needs from the forecaster's forward pass (none by default).

        Args:
            td (TensorDictBase): the batch (a shallow copy of the caller's), changed in place.

        Returns:
            ``td``.
        """
        return td

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        """The loss terms from the forecaster's outputs (each subclass computes its own).

        Args:
            td (TensorDictBase): the batch after :meth:`prepare` and the forecaster's forward pass.

        Returns:
            The ``loss_*`` entries and diagnostics.
        """
        raise NotImplementedError

    def forward(self, td: TensorDictBase) -> TensorDict:
        """:meth:`prepare`, the forecaster and :meth:`loss_from_outputs` on a shallow copy of ``td``.

        Args:
            td (TensorDictBase): a batch following `mmf_rl.keys`, with ``"target"``; not changed.

        Returns:
            The ``loss_*`` entries and diagnostics.
        """
        return self.loss_from_outputs(self.forecaster(self.prepare(td.clone(False))))

    def _get(self, td: TensorDictBase, key):
        value = td.get(key, None)
        if value is None:
            raise KeyError(
                f"{type(self).__name__}: key {key} not found in the forecaster's outputs; "
                f"was the forecaster run on this batch (and with this loss's prepare())?"
            )
        return value
