"""DLow's objective for a learned sampler of ``K`` forecasts (Yuan & Kitani 2020; AgentFormer's weights)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import ForecasterLossBase, gaussian_kl_to_standard, reduce_batch


class DiverseSamplingLoss(ForecasterLossBase):
    """Trains a forecaster's learned sampler (:mod:`mmf_rl.models.latent_sampler`), the forecaster frozen.

    For each history the sampler's ``K`` forecasts ``ŷ_k`` (in the target's units: the normalised
    forecasts times ``target_scale``) are scored by
    - ``loss_best_of_k``: ``min_k Σ_t ||ŷ_k,t - y_t||²``, so that one of the ``K`` is close;
    - ``loss_diversity``: the mean over pairs ``j < k`` of ``exp(-||ŷ_j - ŷ_k||² / diversity_scale)``, so
      that the others spread over the futures the history allows;
    - ``loss_kl``: ``Σ_k KL(N(b_k, a_k²) || N(0, I))`` of the codes and spreads in the prior's standard
      coordinates, at least ``kl_floor`` nats (below it the term stops pulling): the codes stay where the
      prior, which the decoder was trained against, puts mass.
    Each weighted. The defaults are AgentFormer's ETH/UCY setting for hotel, zara1 and zara2 (eth's pushes
    harder, 20 / 10), which did as well as any of its settings on the five folds' validation scenes;
    ``diversity_scale`` is in square metres there: for a target in other units, scale it.

    Each present modality that is not required is dropped with probability ``drop_prob`` per window
    (one always stays): the sampler then learns codes for every presence pattern it may meet.

    Args:
        forecaster (nn.Module): a :class:`~mmf_rl.models.MultimodalForecaster` with ``learned_samples > 0``.
        target_scale (torch.Tensor, optional): ``[D]``, the target's units per normalised unit (its std);
            ``None``: ones.
        best_of_k_weight (float, optional): the weight of ``loss_best_of_k``. Defaults to ``5.0``.
        diversity_weight (float, optional): the weight of ``loss_diversity``. Defaults to ``5.0``.
        diversity_scale (float, optional): the squared distance between two forecasts at which their closeness
            is ``1/e``.
        kl_weight (float, optional): the weight of ``loss_kl``. Defaults to ``0.1``.
        kl_floor (float, optional): the KL below which ``loss_kl`` is constant (nats per history, over all
            ``K`` codes). Defaults to ``10.0``.
        drop_prob (float, optional): the probability of dropping each droppable present modality. Defaults
            to ``0.5``.
        reduction (str, optional): ``"mean"`` (default) | ``"sum"`` | ``"none"`` over the batch.

    Calling it on a batch returns ``loss_best_of_k``, ``loss_diversity`` and ``loss_kl``, each weighted.

    Raises:
        ValueError: a forecaster without a learned sampler, ``diversity_scale <= 0``, ``drop_prob``
            outside ``[0, 1)``, or an unknown ``reduction``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import DiverseSamplingLoss
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2, learned_samples=3,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> loss = DiverseSamplingLoss(model).train()  # the sampler trains, the forecaster stays in eval
        >>> model.training, model.latent_sampler.training
        (False, True)
        >>> sorted(loss(batch).keys())
        ['loss_best_of_k', 'loss_diversity', 'loss_kl']
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys the loss reads; ``set_keys(name=key)`` renames one.

        Attributes:
            target (NestedKey): the future ``y``, ``[B, T, D]``. Defaults to ``"target"``.
        """

        target: NestedKey = keys.TARGET

    default_keys = _AcceptedKeys
    out_keys = ["loss_best_of_k", "loss_diversity", "loss_kl"]

    def __init__(
        self,
        forecaster,
        target_scale: torch.Tensor | None = None,
        best_of_k_weight: float = 5.0,
        diversity_weight: float = 5.0,
        diversity_scale: float = 5.0,
        kl_weight: float = 0.1,
        kl_floor: float = 10.0,
        drop_prob: float = 0.5,
        reduction: str = "mean",
    ):
        super().__init__(forecaster, reduction)
        if getattr(forecaster, "latent_sampler", None) is None:
            raise ValueError(
                "DiverseSamplingLoss trains a learned sampler: build the forecaster with "
                "learned_samples=K > 0"
            )
        if not diversity_scale > 0:
            raise ValueError(f"diversity_scale must be > 0, found {diversity_scale}")
        if not 0 <= drop_prob < 1:
            raise ValueError(f"drop_prob must be in [0, 1), found {drop_prob}")
        scale = torch.ones(forecaster.config.target_dim) if target_scale is None else target_scale
        self.register_buffer("target_scale", torch.as_tensor(scale, dtype=torch.float32).flatten())
        self.weights = {"best_of_k": best_of_k_weight, "diversity": diversity_weight, "kl": kl_weight}
        self.diversity_scale, self.kl_floor, self.drop_prob = diversity_scale, kl_floor, drop_prob

    def train(self, mode: bool = True):
        """Only the sampler trains: the forecaster stays in eval mode, as it forecasts at test time."""
        super().train(mode)
        self.forecaster.eval()
        self.forecaster.latent_sampler.train(mode)
        return self

    def _loss_in_keys(self) -> list:
        return [self.tensor_keys.target]

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        specs = self.forecaster.modalities
        present = torch.stack([td.get(s.present_key) for s in specs], -1)
        droppable = torch.tensor([not s.required for s in specs], device=present.device)
        kept = present & ~((torch.rand(present.shape, device=present.device) < self.drop_prob) & droppable)
        nothing_left = ~kept.any(-1, keepdim=True)
        kept = torch.where(nothing_left, present, kept)
        for i, spec in enumerate(specs):
            td.set(spec.present_key, kept[:, i])
        return td

    def forward(self, td: TensorDictBase) -> TensorDict:
        td = self.prepare(td.clone(False))
        samples, codes, spreads = self.forecaster.learned_samples(td)
        target = self._get(td, self.tensor_keys.target)
        forecasts = samples * self.target_scale  # [B, K, T, D] in the target's units
        best = (forecasts - (target * self.target_scale).unsqueeze(1)).square().sum((-2, -1)).amin(1)
        flat = forecasts.flatten(2)
        # Squared distances by difference, not cdist: cdist's gradient is NaN where two forecasts coincide.
        distance = (flat.unsqueeze(2) - flat.unsqueeze(1)).square().sum(-1)
        j, k = torch.triu_indices(flat.shape[1], flat.shape[1], 1, device=flat.device)
        closeness = (-distance[:, j, k] / self.diversity_scale).exp().mean(-1)
        # The spreads' signs carry nothing; the floor keeps the log finite where a spread is 0.
        kl = gaussian_kl_to_standard(codes, (spreads.square() + 1e-8).sqrt()).sum((1, 2))
        return TensorDict(
            loss_best_of_k=self.weights["best_of_k"] * reduce_batch(best, self.reduction),
            loss_diversity=self.weights["diversity"] * reduce_batch(closeness, self.reduction),
            loss_kl=self.weights["kl"] * reduce_batch(kl, self.reduction).clamp_min(self.kl_floor),
        )
