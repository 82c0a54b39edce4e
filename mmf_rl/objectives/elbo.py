"""The CVAE evidence lower bound: Gaussian NLL of the future + KL of the posterior to ``N(0, I)``."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import ForecasterLossBase, gaussian_kl_to_standard, gaussian_nll, reduce_batch


class ELBOLoss(ForecasterLossBase):
    """``-ELBO = E_q[-log p(y | X, z)] + β KL(q(z | X, y) || N(0, I))`` (paper, "Model Learning").

    Both terms are summed over their dims (``T × D`` for the NLL, ``d_z`` for the KL) and reduced
    over the batch. The KL is analytic; ``z`` is drawn by the forecaster with the
    reparameterisation trick, one sample per row.

    Args:
        forecaster: a :class:`~mmf_rl.models.MultimodalForecaster` (or any module writing the
            same keys).
        kl_weight: ``β`` once warm.
        kl_warmup_steps: ``β`` grows linearly from ``kl_weight / kl_warmup_steps`` to
            ``kl_weight`` over this many training updates (0: constant). The update count is a
            buffer, so it is saved and restored with the loss's ``state_dict``.
        reduction: ``"mean"`` | ``"sum"`` | ``"none"`` over the batch.

    Returns a TensorDict with ``loss_nll``, ``loss_kl`` (already weighted by ``β``) and the
    detached diagnostics ``kl`` (unweighted) and ``kl_weight``.
    """

    @dataclass
    class _AcceptedKeys:
        target: NestedKey = keys.TARGET
        forecast_loc: NestedKey = keys.FORECAST_LOC
        forecast_scale: NestedKey = keys.FORECAST_SCALE
        posterior_loc: NestedKey = keys.POSTERIOR_LOC
        posterior_scale: NestedKey = keys.POSTERIOR_SCALE

    default_keys = _AcceptedKeys
    out_keys = ["loss_nll", "loss_kl", "kl", "kl_weight"]

    def __init__(self, forecaster, *, kl_weight: float = 1.0, kl_warmup_steps: int = 0, reduction: str = "mean"):
        super().__init__(forecaster, reduction)
        if kl_weight < 0 or kl_warmup_steps < 0:
            raise ValueError(f"kl_weight and kl_warmup_steps must be >= 0, found {kl_weight}, {kl_warmup_steps}")
        self.kl_weight = kl_weight
        self.kl_warmup_steps = kl_warmup_steps
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))

    def _loss_in_keys(self) -> list:
        k = self.tensor_keys
        return [k.target, k.forecast_loc, k.forecast_scale, k.posterior_loc, k.posterior_scale]

    def current_kl_weight(self) -> float:
        if not self.kl_warmup_steps:
            return self.kl_weight
        return self.kl_weight * min(1.0, (int(self.num_updates) + 1) / self.kl_warmup_steps)

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        target = self._get(td, k.target)
        nll = gaussian_nll(target, self._get(td, k.forecast_loc), self._get(td, k.forecast_scale)).flatten(1).sum(-1)
        kl = gaussian_kl_to_standard(self._get(td, k.posterior_loc), self._get(td, k.posterior_scale)).sum(-1)
        beta = self.current_kl_weight()
        if self.training and torch.is_grad_enabled():
            self.num_updates += 1
        return TensorDict(
            loss_nll=reduce_batch(nll, self.reduction),
            loss_kl=beta * reduce_batch(kl, self.reduction),
            kl=kl.mean().detach(),
            kl_weight=torch.tensor(beta),
        )
