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

    Args:
        *losses (ForecasterLossBase): the losses, all of the same forecaster instance.

    Raises:
        ValueError: no loss, losses of different forecasters, or two losses that write the same entry
            (when called).
        TypeError: a loss after the first that is not a :class:`ForecasterLossBase` (the first is read
            for its ``forecaster`` before the check: an ``AttributeError`` when it has none).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import CombinedLoss, ELBOLoss, MissingModalityLoss
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> loss = CombinedLoss(ELBOLoss(model), MissingModalityLoss(model))
        >>> out = loss(batch)  # one forward pass for both
        >>> sorted(key for key in out.keys() if key.startswith("loss_"))
        ['loss_kl', 'loss_mis', 'loss_nll']
        >>> sum(value for key, value in out.items() if key.startswith("loss_")).backward()
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
