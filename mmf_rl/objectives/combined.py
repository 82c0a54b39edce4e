"""Several forecaster losses over one forward pass."""

from __future__ import annotations

from tensordict import TensorDict, TensorDictBase
from torch import nn

from mmf_rl.objectives.common import ForecasterLossBase


class CombinedLoss(ForecasterLossBase):
    """Runs each loss's ``prepare``, the shared forecaster **once**, then each loss.

    ``CombinedLoss(ELBOLoss(model), MissingModalityLoss(model))(batch)`` returns ``loss_nll``,
    ``loss_kl`` and ``loss_mis`` (plus diagnostics) from a single forward pass whose decoder
    handles the teacher and student decodes in one batched call. The trainer sums ``loss_*``.
    """

    def __init__(self, *losses: ForecasterLossBase):
        if not losses:
            raise ValueError("CombinedLoss needs at least one loss")
        forecaster = losses[0].forecaster
        for loss in losses:
            if not isinstance(loss, ForecasterLossBase):
                raise TypeError(f"CombinedLoss takes forecaster losses, found {type(loss).__name__}")
            if loss.forecaster is not forecaster:
                raise ValueError("CombinedLoss: every loss must wrap the same forecaster instance")
        super().__init__(forecaster)
        self.losses = nn.ModuleList(losses)

    @property
    def in_keys(self):
        return sorted({k for loss in self.losses for k in loss.in_keys}, key=str)

    @property
    def out_keys(self):
        return [k for loss in self.losses for k in loss.out_keys]

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        for loss in self.losses:
            td = loss.prepare(td)
        return td

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        out = TensorDict()
        for loss in self.losses:
            terms = loss.loss_from_outputs(td)
            clash = set(terms.keys()) & set(out.keys())
            if clash:
                raise ValueError(f"CombinedLoss: losses write the same entries {sorted(clash)}")
            out.update(terms)
        return out
