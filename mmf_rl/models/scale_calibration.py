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

**The level curve.** One factor matches one coverage level; the output family's shape decides the
others, and standardised errors more peaked or heavier-tailed than the family cover more than 50% at
its 50% level when the factor holds 90%. So each pattern also holds a level curve: at each central
level ``L_k`` of :data:`LEVELS`, ``level_factors[p, k]``, the half width of the pattern's central
``L_k`` interval in units of its calibrated scale, divided by the family's (``half_width(L_k)``). Ones
(the built, never-fitted and pre-curve state) are the family's own intervals. Fitted
(``mmf-rl calibrate method=levels``) the curve's entry at 90% is 1 (the factor already holds 90%):
the scale, and everything that reads one scale (the NLL losses and ``eval``'s NLL, the world model,
the RL transforms), is the family at the pattern's 90% scale, and only the intervals, their
coverage and width, and the CRPS read the curve (:func:`level_half_widths`, the recalibrated
quantile function of Kuleshov, Fenner & Ermon 2018, per presence pattern).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import torch
from torch import nn

from mmf_rl.objectives.distributions import OutputDistribution

# The central-interval levels of the level curve. Evenly spaced over the body (0.1 to 0.9), as the
# CRPS weighs every quantile level alike and the curve is interpolated between them; 0.95 and 0.99 for
# the tail, where the heavy-tailed errors depart most from the family; none beyond 0.99, where a
# pattern's fit would rest on under 1% of its values (a few windows' worth at min_windows=32). 0.5
# and 0.9, the levels `eval` reports, are grid levels, fitted, not interpolated.
LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99)


class PresenceScaleCalibration(nn.Module):
    """``2^M`` scale factors indexed by presence pattern, their ``2^M × T`` step factors and the
    patterns' level curves, ``2^M × len(LEVELS)`` (see module docstring).

    Args:
        num_modalities (int): ``M``, the model's modalities (``factors`` has ``2^M`` entries).
        horizon (int): ``T``, the forecast's steps (``step_factors`` is ``[2^M, T]``).
    """

    def __init__(self, num_modalities: int, horizon: int):
        super().__init__()
        self.num_modalities = num_modalities
        self.register_buffer("factors", torch.ones(2**num_modalities))
        self.register_buffer("step_factors", torch.ones(2**num_modalities, horizon))
        self.register_buffer("level_factors", torch.ones(2**num_modalities, len(LEVELS)))
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
        self.level_factors.fill_(1.0)

    def has_step_factors(self) -> bool:
        """Whether a horizon step is scaled apart from its pattern (a ``per_step`` fit)."""
        return bool((self.step_factors != 1).any())

    def has_level_curve(self) -> bool:
        """Whether a pattern's intervals depart from the family's shape (a ``levels`` fit)."""
        return bool((self.level_factors != 1).any())

    def is_identity(self) -> bool:
        return bool((self.factors == 1).all()) and not self.has_step_factors() and not self.has_level_curve()

    def level_curve(self, present: torch.Tensor) -> torch.Tensor:
        """``[N, len(LEVELS)]``: the level curve of each row's pattern (presence ``[N, M]``, spec order)."""
        return self.level_factors[self.pattern_index(present)]

    def state_defaults(self) -> dict[str, torch.Tensor]:
        """What a state saved before the factors, the step factors or the level curves existed lacks:
        ones, its behaviour then (read by :func:`mmf_rl.checkpoint.state_with_defaults`)."""
        return {
            "factors": torch.ones_like(self.factors),
            "step_factors": torch.ones_like(self.step_factors),
            "level_factors": torch.ones_like(self.level_factors),
        }


def pattern_name(index: int, names: list[str]) -> str:
    """``"image+force"``: the modalities present in pattern ``index`` (spec order)."""
    return "+".join(name for i, name in enumerate(names) if index >> i & 1)


@functools.cache
def family_half_widths(family: OutputDistribution, levels: tuple[float, ...]) -> torch.Tensor:
    """``[len(levels)]`` float64: the half widths of the central ``levels`` intervals of the family's
    standard member (computed once per family and levels)."""
    return torch.tensor([family.half_width(level) for level in levels], dtype=torch.float64)


def level_half_widths(
    level_factors: torch.Tensor, levels: Sequence[float], family: OutputDistribution
) -> torch.Tensor:
    """The half widths, in units of the calibrated scale, of the central ``levels`` intervals under
    level curves ``level_factors`` ``[..., len(LEVELS)]`` (ones: the family's own,
    ``family.half_width(level)``).

    The curve's half widths ``h_k = level_factors[k] · half_width(L_k)`` are placed at the family's
    ``u_k = half_width(L_k)``, and a level ``L`` maps through the piecewise-linear function of
    ``u = half_width(L)`` through ``(0, 0)`` and every ``(u_k, h_k)``, continued beyond the last node
    by the ray ``u · h_K / u_K``: the family's distribution of ``|z|`` pushed through a nondecreasing
    map, so the recalibrated distribution is a distribution (its quantiles never cross), it holds the
    fitted half width at every grid level, and under ones it is the family itself. Nondecreasing half
    widths ``h_k`` are the caller's (the fit takes their cumulative maximum); this function takes the
    running maximum again, so any input gives monotone intervals.

    Args:
        level_factors (torch.Tensor): ``[..., len(LEVELS)]``, positive.
        levels (Sequence[float]): central levels in ``(0, 1)``.
        family (OutputDistribution): the output family.

    Returns:
        ``[..., len(levels)]`` half widths (``level_factors``' dtype).

    Examples:
        >>> import torch
        >>> from mmf_rl.models.scale_calibration import LEVELS, level_half_widths
        >>> from mmf_rl.objectives import output_distribution
        >>> normal = output_distribution("normal")
        >>> level_half_widths(torch.ones(len(LEVELS)), [0.5, 0.9], normal)  # the family's own
        tensor([0.6745, 1.6449])
    """
    dtype = level_factors.dtype
    nodes = family_half_widths(family, LEVELS).to(level_factors.device)
    query = family_half_widths(family, tuple(float(level) for level in levels)).to(level_factors.device)
    heights = (level_factors.double() * nodes).cummax(-1).values
    zero = heights.new_zeros(*heights.shape[:-1], 1)
    heights = torch.cat([zero, heights], -1)  # [..., K + 1], the node (0, 0) first
    nodes = torch.cat([nodes.new_zeros(1), nodes])
    # The segment of each query level: nodes[j - 1] <= u <= nodes[j], j in 1..K.
    right = torch.searchsorted(nodes, query).clamp(1, len(LEVELS))
    left = right - 1
    share = (query - nodes[left]) / (nodes[right] - nodes[left])
    inside = heights[..., left] + share * (heights[..., right] - heights[..., left])
    beyond = query * (heights[..., -1:] / nodes[-1])
    return torch.where(query > nodes[-1], beyond, inside).to(dtype)
