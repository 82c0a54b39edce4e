"""Constant velocity: the parameter-free reference of trajectory forecasting (Schöller et al. 2020).

It extrapolates the last step of the target's own past (``"target_past"``, which a data config
with ``include_target_past: true`` adds to every batch) over the horizon. As a registered model
it goes through the same windows, presence subsets and metric code as the trained models, so its
score checks the evaluation protocol itself. It reads no modality (its forecast is the same in
every presence subset) and has nothing to train.

``sample`` draws ``K`` forecasts: with ``heading_noise = 0`` all equal to the point forecast; with
``heading_noise = σ > 0`` (planar targets) each turns the last velocity by an angle drawn from
``N(0, σ²)`` and keeps its speed: the sampled variant of Schöller et al. Targets are normalised
per dim, so the turn is made in the target's units: ``target_scale`` is the data's per-dim target
std (``Normalizer.stats["target/std"]``; default 1, a target in units).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.models.baselines.common import BaselineConfig, DeterministicForecaster
from mmf_rl.models.registry import register_model


def constant_velocity(target_past: torch.Tensor, horizon: int) -> torch.Tensor:
    """Extrapolate the last step of a past trajectory over the horizon.

    In the normalised target frame this is the normalised extrapolation in the target's units: each
    forecast step ``x_H + k (x_H - x_{H-1})`` is an affine combination of two past positions (weights
    ``1 + k`` and ``-k``, summing to 1), so it commutes with the per-dim ``(x - mean) / std`` of the
    :class:`~mmf_rl.datasets.splits.Normalizer` (and with the anchor a relative target subtracts).

    Args:
        target_past (torch.Tensor): ``[B, H, D]``, ``H >= 2``.
        horizon (int): ``T``, steps to extrapolate.

    Returns:
        ``[B, T, D]``: the last position plus ``1..T`` times the last step.

    Examples:
        >>> import torch
        >>> from mmf_rl.models.baselines.constant_velocity import constant_velocity
        >>> constant_velocity(torch.tensor([[[0.0, 0.0], [1.0, 0.5]]]), 2)
        tensor([[[2.0000, 1.0000],
                 [3.0000, 1.5000]]])
    """
    return extrapolate(target_past[:, -1], target_past[:, -1] - target_past[:, -2], horizon)


def extrapolate(position: torch.Tensor, velocity: torch.Tensor, horizon: int) -> torch.Tensor:
    """``[..., D]`` position and velocity -> ``[..., T, D]`` positions ``1..T`` steps ahead."""
    steps = torch.arange(1, horizon + 1, dtype=position.dtype, device=position.device)
    return position.unsqueeze(-2) + velocity.unsqueeze(-2) * steps[:, None]


def target_past_of(td: TensorDictBase, reader: str, target_dim: int | None = None) -> torch.Tensor:
    """``td``'s ``"target_past"`` ``[B, H >= 2, D]``, or a ``KeyError`` naming ``reader`` (what needs it)
    and the data config key that adds it (``include_target_past: true``)."""
    past = td.get(keys.TARGET_PAST, None)
    dims_ok = past is not None and (target_dim is None or past.shape[-1] == target_dim)
    if past is None or past.dim() != 3 or past.shape[1] < 2 or not dims_ok:
        expected = "D" if target_dim is None else str(target_dim)
        raise KeyError(
            f"{reader} needs {keys.TARGET_PAST!r} [B, H >= 2, {expected}] in the batch, found "
            f"{None if past is None else list(past.shape)}; set include_target_past: true in the data "
            "config"
        )
    return past


@dataclass
class ConstantVelocityConfig(BaselineConfig):
    """:class:`BaselineConfig` of :class:`ConstantVelocity`, plus its sampler's settings.

    Args:
        modalities (list[ModalitySpec]): one :class:`ModalitySpec` per input modality (at least one).
        history (int, optional): ``H``, past steps per window. Defaults to ``10``.
        horizon (int, optional): ``T``, future steps forecast. Defaults to ``10``.
        target_dim (int, optional): ``D``, dims of the forecast variable. Defaults to ``2``.
        d_model (int, optional): width of every per-modality representation. Defaults to ``64``.
        head_hidden (int, optional): hidden width of the output head. Defaults to ``256``.
        min_scale (float, optional): floor added to every predicted scale. Defaults to
            ``1e-3``.
        nonfinite (str, optional): NaN/Inf under a present modality: ``"raise"`` (default) or
            ``"absent"`` (read as absent), as :func:`mmf_rl.keys.mark_nonfinite_absent` applies it.
        output_distribution (str, optional): the family the forecast's ``(loc, scale)`` is read with:
            ``"normal"`` (default), ``"laplace"`` or ``"student_t"`` (:mod:`mmf_rl.objectives.distributions`).
        output_df (float, optional): the degrees of freedom of ``"student_t"`` (``> 2``). Defaults to ``4``.
        heading_noise (float, optional): radians, the std of the turn of each sample (``0``, the default:
            every sample is the point forecast); needs ``target_dim = 2``.
        target_scale (list[float], optional): the per-dim std of the normalised target, so the turn is
            made in the target's units; ``None``: 1.

    Raises:
        ValueError: no modality, duplicate names, an unknown encoder, a size below 1, ``min_scale <= 0``, an
            unknown ``nonfinite`` or ``output_distribution``, ``output_df <= 2`` with ``"student_t"``, a
            negative ``heading_noise``, ``heading_noise`` with ``target_dim != 2``, or ``target_scale`` not
            ``target_dim`` positive numbers.
    """

    heading_noise: float = 0.0
    target_scale: list[float] | None = None

    def __post_init__(self):
        super().__post_init__()
        if not self.heading_noise >= 0:
            raise ValueError(f"ConstantVelocityConfig.heading_noise must be >= 0, found {self.heading_noise}")
        if self.heading_noise > 0 and self.target_dim != 2:
            raise ValueError(
                f"ConstantVelocityConfig.heading_noise turns a planar velocity: target_dim must be 2, found "
                f"{self.target_dim}; set heading_noise=0"
            )
        if self.target_scale is not None:
            self.target_scale = [float(s) for s in self.target_scale]
            if len(self.target_scale) != self.target_dim or min(self.target_scale) <= 0:
                raise ValueError(
                    f"ConstantVelocityConfig.target_scale must be {self.target_dim} positive stds (one per "
                    f"target dim), found {self.target_scale}"
                )


@register_model("constant_velocity", ConstantVelocityConfig, loss=("nll",))
class ConstantVelocity(DeterministicForecaster):
    """Extrapolates the last step of ``"target_past"``; unit scale (see module docstring).

    Reads ``"target_past"`` ``[B, H, D]`` (``H >= 2``; a missing one is a ``KeyError`` when called) and
    writes ``("forecast", "loc"/"scale")``. The modalities are validated but never read.

    Args:
        config (ConstantVelocityConfig): the sizes and the sampler's settings.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models.baselines import ConstantVelocity, ConstantVelocityConfig
        >>> config = ConstantVelocityConfig([ModalitySpec("pose", "vector", (3,))], history=3, horizon=2)
        >>> batch = TensorDict({
        ...     ("obs", "pose"): torch.zeros(1, 3), ("present", "pose"): torch.ones(1, dtype=torch.bool),
        ...     "target_past": torch.tensor([[[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]]]),
        ... }, batch_size=[1])
        >>> ConstantVelocity(config)(batch)["forecast", "loc"]
        tensor([[[3.0000, 1.5000],
                 [4.0000, 2.0000]]])
    """

    def __init__(self, config: ConstantVelocityConfig):
        super().__init__(config)
        self.in_keys = [*self.in_keys, keys.TARGET_PAST]
        scale = config.target_scale or [1.0] * config.target_dim
        self.register_buffer("target_scale", torch.tensor(scale))

    def _last_step(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        past = target_past_of(td, "constant velocity")
        return past[:, -1], past[:, -1] - past[:, -2]

    def forecast(self, td):
        loc = constant_velocity(target_past_of(td, "constant velocity"), self.config.horizon)
        return loc, torch.ones_like(loc)

    def sample(self, td: TensorDictBase, num_samples: int = 20) -> TensorDictBase:
        """Write ``("forecast", "samples")`` ``[B, K, T, D]``: the point forecast, each sample's last
        velocity turned by an angle drawn from ``N(0, heading_noise²)`` (global RNG).

        Args:
            td (TensorDictBase): a batch with ``"target_past"``; written in place.
            num_samples (int, optional): ``K``. Defaults to ``20``.

        Returns:
            ``td``.
        """
        if self.config.heading_noise == 0:
            return super().sample(td, num_samples)
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, found {num_samples}")
        self.validate(td)
        position, velocity = self._last_step(td)
        angle = (
            torch.randn(velocity.shape[0], num_samples, device=velocity.device) * self.config.heading_noise
        )
        cos, sin = angle.cos(), angle.sin()
        vx, vy = (velocity * self.target_scale).unbind(-1)  # [B] each, in the target's units
        turned = torch.stack(
            [cos * vx[:, None] - sin * vy[:, None], sin * vx[:, None] + cos * vy[:, None]], -1
        )
        samples = extrapolate(
            position[:, None].expand_as(turned), turned / self.target_scale, self.config.horizon
        )
        td.set(keys.FORECAST_SAMPLES, samples)
        return td
