"""Negative log-likelihood of the future under the forecast's distribution: the loss of the deterministic
baselines."""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import ForecasterLossBase, reduce_batch
from mmf_rl.objectives.distributions import output_distribution_of
from mmf_rl.objectives.registry import register_loss_term


@register_loss_term("nll")
class GaussianNLLLoss(ForecasterLossBase):
    """``-log p(y; loc, scale)`` summed over ``T × D`` and reduced over the batch.

    For forecasters without a latent (LF-LSTM, MulT): the same likelihood term as the ELBO's
    ``loss_nll``, so every model is fitted to the same objective on the forecast. ``p`` is the
    forecaster's output distribution (its config's ``output_distribution``,
    :func:`~mmf_rl.objectives.output_distribution_of`): ``N(loc, scale²)`` by default, hence the name.

    Args:
        forecaster (nn.Module): any module writing ``("forecast", "loc"/"scale")``.
        reduction (str, optional): ``"mean"`` (default) | ``"sum"`` | ``"none"`` over the batch.

    Calling it on a batch returns a TensorDict with ``loss_nll``. The loss config has no setting for it.

    Raises:
        ValueError: an unknown ``reduction``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import GaussianNLLLoss
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> loss = GaussianNLLLoss(model)
        >>> out = loss(batch)  # runs the model on a shallow copy: `batch` is left as it was
        >>> out
        TensorDict(
            fields={
                loss_nll: Tensor(shape=torch.Size([]), device=cpu, dtype=torch.float32, is_shared=False)},
            batch_size=torch.Size([]),
            device=None,
            is_shared=False)
        >>> out["loss_nll"].backward()
        >>> GaussianNLLLoss(model, reduction="none")(batch)["loss_nll"].shape  # one per sample
        torch.Size([8])
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys the loss reads; ``set_keys(name=key)`` renames one.

        Attributes:
            target (NestedKey): the future ``y``, ``[B, T, D]``. Defaults to ``"target"``.
            forecast_loc (NestedKey): the forecast's mean, ``[B, T, D]``. Defaults to
                ``("forecast", "loc")``.
            forecast_scale (NestedKey): the forecast's scale (the Gaussian's standard deviation),
                ``[B, T, D]``. Defaults to ``("forecast", "scale")``.
        """

        target: NestedKey = keys.TARGET
        forecast_loc: NestedKey = keys.FORECAST_LOC
        forecast_scale: NestedKey = keys.FORECAST_SCALE

    default_keys = _AcceptedKeys
    out_keys = ["loss_nll"]

    def __init__(self, forecaster, reduction: str = "mean"):
        super().__init__(forecaster, reduction)
        self.output_distribution = output_distribution_of(forecaster)

    def _loss_in_keys(self) -> list:
        k = self.tensor_keys
        return [k.target, k.forecast_loc, k.forecast_scale]

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        nll = self.output_distribution.nll(
            self._get(td, k.target), self._get(td, k.forecast_loc), self._get(td, k.forecast_scale)
        )
        return TensorDict(loss_nll=reduce_batch(nll.flatten(1).sum(-1), self.reduction))
