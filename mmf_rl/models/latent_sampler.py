"""A learned sampler of ``K`` latents per history: DLow (Yuan & Kitani 2020), as AgentFormer uses it.

``K`` independent draws from the prior ``p(z | X)`` cover the futures badly: two of twenty may fall
together and none near a rare turn, which best-of-``K`` metrics (minADE20) punish. DLow trains, on a
frozen CVAE, a small network that maps the history's features to ``K`` latent codes at once, each
decoded to one forecast, with a best-of-``K`` reconstruction term, a term that pushes the ``K``
forecasts apart and a KL term that keeps every code where the prior puts mass
(:class:`~mmf_rl.objectives.DiverseSamplingLoss`).

Each code is ``b_k`` with a spread ``a_k`` in the prior's standard coordinates: ``z_k = μ_p + σ_p ⊙
b_k``. Forecasts decode the codes themselves, not draws around them (AgentFormer's ``train_w_mean``):
the ``K`` forecasts of a history are deterministic. ``a_k`` enters only the KL term, ``KL(N(b_k,
a_k²) || N(0, I))``, which equals the KL of ``N(μ_p + σ_p b_k, σ_p² a_k²)`` to the prior itself.
"""

from __future__ import annotations

import torch
from torch import nn

# The q-net's hidden widths (DLow's and AgentFormer's ETH/UCY setting).
HIDDEN = (512, 256)


class LatentSampler(nn.Module):
    """``features [N, F] -> (codes [N, K, d_z], spreads [N, K, d_z])`` in the prior's standard coordinates.

    Args:
        feature_dim: ``F``, the width of the forecaster's fused representation of a history.
        d_latent: ``d_z``.
        num_samples: ``K``, the codes made per history.
    """

    def __init__(self, feature_dim: int, d_latent: int, num_samples: int):
        super().__init__()
        self.num_samples, self.d_latent = num_samples, d_latent
        self.trunk = nn.Sequential(
            nn.Linear(feature_dim, HIDDEN[0]), nn.Tanh(), nn.Linear(HIDDEN[0], HIDDEN[1]), nn.Tanh()
        )
        self.codes = nn.Linear(HIDDEN[1], num_samples * d_latent)
        self.spreads = nn.Linear(HIDDEN[1], num_samples * d_latent)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hidden = self.trunk(features)
        shape = (features.shape[0], self.num_samples, self.d_latent)
        return self.codes(hidden).view(shape), self.spreads(hidden).view(shape)
