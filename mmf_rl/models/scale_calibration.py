"""Post-hoc recalibration of the forecast's scale, one factor per presence pattern (and horizon step).

A model's Gaussian scale head can be over- or under-confident, and differently for each set of
present sensors (on push the paper model's intervals are too narrow mostly when a single
modality is left; see docs/results.md). One global temperature cannot fix subsets that err both
ways, so every registered model holds a
:class:`PresenceScaleCalibration`: ``2^M`` factors, one per presence pattern (``M`` modalities in
the model's spec order; pattern ``sum_i present_i << i``; pattern 0, nothing present, is never
used), that multiply ``("forecast", "scale")``, and ``2^M × T`` step factors that refine them per
horizon step (step ``t`` of pattern ``p`` is scaled by ``factors[p] · step_factors[p, t]``: a
pattern's error can grow with the horizon faster than its scale does). All ones (what a model is
built with, and what a model saved before either existed loads with) is exactly the uncalibrated
forecast.

The factors apply in eval mode only. They are fitted after training, on held-out windows
(:func:`mmf_rl.eval.scale_fit.fit_scale_calibration`, ``mmf-rl calibrate``; the step factors with
``per_step=true``), for the weights they were fitted with: the training losses must see the head's
own scale, so that factors carried into further training (a resumed or fine-tuned run) cannot bias
its gradients.
"""

from __future__ import annotations

import torch
from torch import nn


class PresenceScaleCalibration(nn.Module):
    """``2^M`` scale factors indexed by presence pattern, and their ``2^M × T`` step factors (see
    module docstring).

    Args:
        num_modalities (int): ``M``, the model's modalities (``factors`` has ``2^M`` entries).
        horizon (int): ``T``, the forecast's steps (``step_factors`` is ``[2^M, T]``).
    """

    def __init__(self, num_modalities: int, horizon: int):
        super().__init__()
        self.num_modalities = num_modalities
        self.register_buffer("factors", torch.ones(2**num_modalities))
        self.register_buffer("step_factors", torch.ones(2**num_modalities, horizon))
        self.register_buffer("bits", 2 ** torch.arange(num_modalities), persistent=False)

    def pattern_index(self, present: torch.Tensor) -> torch.Tensor:
        """``[N]`` long: the pattern of each row of presence ``[N, M]`` (bool, spec order)."""
        return (present.long() * self.bits).sum(-1)

    def forward(self, scale: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """``scale`` ``[N, T, ...]`` times its row's factor and its step's (eval mode; unchanged in train
        mode).

        No Python branch on values: one `torch.jit.trace` serves every presence pattern."""
        if self.training:
            return scale
        pattern = self.pattern_index(present)
        factor = self.factors[pattern].unsqueeze(1) * self.step_factors[pattern]
        return scale * factor.view(*factor.shape, *[1] * (scale.dim() - 2))

    @torch.no_grad()
    def reset(self) -> None:
        """Back to ones (the uncalibrated forecast), in place (a traced graph sees the change)."""
        self.factors.fill_(1.0)
        self.step_factors.fill_(1.0)

    def has_step_factors(self) -> bool:
        """Whether a horizon step is scaled apart from its pattern (a ``per_step`` fit)."""
        return bool((self.step_factors != 1).any())

    def is_identity(self) -> bool:
        return bool((self.factors == 1).all()) and not self.has_step_factors()

    def state_defaults(self) -> dict[str, torch.Tensor]:
        """What a state saved before the factors or the step factors existed lacks: ones, its behaviour
        then (read by :func:`mmf_rl.checkpoint.state_with_defaults`)."""
        return {"factors": torch.ones_like(self.factors), "step_factors": torch.ones_like(self.step_factors)}


def pattern_name(index: int, names: list[str]) -> str:
    """``"image+force"``: the modalities present in pattern ``index`` (spec order)."""
    return "+".join(name for i, name in enumerate(names) if index >> i & 1)
