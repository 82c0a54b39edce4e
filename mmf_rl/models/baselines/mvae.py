"""MVAE: a product-of-experts latent over the present modalities (Wu & Goodman 2018).

Each modality ``m`` has an expert ``q_m(z | x_m) = N(μ_m, σ_m²)`` (the forecaster's window
encoder, then a linear layer). The joint posterior is the product of the present experts and
a prior expert ``N(0, I)``:

    precision = 1 + Σ_{m present} σ_m⁻²,   μ = (Σ_{m present} μ_m σ_m⁻²) / precision,

so a missing modality is simply a missing factor: no zero-fill, no imputation. A decoder MLP
maps ``z`` to the Gaussian over the ``T × D`` future; training maximises the ELBO
(:class:`~mmf_rl.objectives.ELBOLoss`: NLL of the future + KL of the PoE posterior to
``N(0, I)``).

Choices: as in Lee et al. 2020's use of MVAE for forecasting, the latent is inferred from the
inputs only (``q(z | X)``), so at test time the forecast decodes the posterior mean (or samples
of it: :meth:`MVAE.sample`), not the prior. Wu & Goodman's sub-sampled ELBO terms (each single
modality alone) are not added: the model trains on the presence patterns the data gives, like
the other baselines.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from mmf_rl import keys
from mmf_rl.models.baselines.common import (
    BaselineConfig,
    gaussian_head_output,
    presence,
    student_batch,
    validate_baseline_batch,
    with_student,
)
from mmf_rl.models.encoders import build_encoder, mlp
from mmf_rl.models.hub import PretrainedModel
from mmf_rl.models.registry import register_model
from mmf_rl.models.scale_calibration import PresenceScaleCalibration


@dataclass
class MVAEConfig(BaselineConfig):
    """:class:`BaselineConfig` of :class:`MVAE`, plus its latent.

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
        d_latent (int, optional): ``d_z``. Defaults to ``16``.
        eval_latent (str, optional): the latent ``forward`` decodes in eval mode: ``"mean"`` (default,
            the posterior mean: deterministic) or ``"sample"`` (a posterior draw).

    Raises:
        ValueError: no modality, duplicate names, an unknown encoder, a size below 1, ``min_scale <= 0``, an
            unknown ``nonfinite`` or ``output_distribution``, ``output_df <= 2`` with ``"student_t"``, or an
            unknown ``eval_latent``.
    """

    d_latent: int = 16
    eval_latent: Literal["mean", "sample"] = "mean"

    def __post_init__(self):
        super().__post_init__()
        if self.eval_latent not in ("mean", "sample"):
            raise ValueError(f"MVAEConfig.eval_latent must be 'mean' or 'sample', found {self.eval_latent!r}")


def product_of_experts(loc: torch.Tensor, scale: torch.Tensor, present: torch.Tensor):
    """Experts ``[B, M, d_z]`` with presence ``[B, M]`` times the prior ``N(0, I)`` -> ``loc``, ``scale``."""
    precision = torch.where(present.unsqueeze(-1), scale.pow(-2), torch.zeros((), device=scale.device))
    total = 1.0 + precision.sum(1)
    return (precision * loc).sum(1) / total, total.rsqrt()


@register_model("mvae", MVAEConfig, loss=("elbo",))
class MVAE(TensorDictModuleBase, PretrainedModel):
    """Product-of-experts VAE forecaster (see module docstring).

    Writes ``("forecast", "loc"/"scale")``, ``("posterior", ...)``, ``("prior", ...)`` and
    ``"latent"``. In train mode ``z`` is a reparameterised posterior sample. In eval mode the
    forecast's scale is multiplied by its presence pattern's factor (``scale_calibration``).
    Trained with :class:`~mmf_rl.objectives.ELBOLoss` (its registry entry's loss).

    Args:
        config (MVAEConfig): the sizes and the eval latent.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models.baselines import MVAE, MVAEConfig
        >>> force, pose = ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))
        >>> model = MVAE(MVAEConfig([force, pose], history=4, horizon=5, d_model=16, d_latent=4)).eval()
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(3, 4, 6),
        ...     ("present", "force"): torch.tensor([True, True, False]),  # the third sample lost it
        ...     ("obs", "pose"): torch.randn(3, 3),
        ...     ("present", "pose"): torch.ones(3, dtype=torch.bool),
        ... }, batch_size=[3])
        >>> out = model(batch)
        >>> out["forecast", "loc"].shape, out["posterior", "loc"].shape
        (torch.Size([3, 5, 2]), torch.Size([3, 4]))
        >>> model.sample(batch, num_samples=6)["forecast", "samples"].shape  # K posterior draws
        torch.Size([3, 6, 5, 2])
    """

    # It decodes from its posterior only, so the ELBO refuses the GSNN term (loss.gsnn_weight).
    decodes_from_prior = False

    def __init__(self, config: MVAEConfig):
        super().__init__()
        self.config = config
        self.modalities = list(config.modalities)
        d, dz = config.d_model, config.d_latent
        self.encoders = nn.ModuleDict({s.name: build_encoder(s, config.history, d) for s in self.modalities})
        self.experts = nn.ModuleDict({s.name: nn.Linear(d, 2 * dz) for s in self.modalities})
        self.decoder = mlp(dz, config.head_hidden, 2 * config.horizon * config.target_dim)
        self.scale_calibration = PresenceScaleCalibration(len(self.modalities), config.horizon)
        self.in_keys = [s.obs_key for s in self.modalities] + [s.present_key for s in self.modalities]
        self.out_keys = [
            keys.FORECAST_LOC,
            keys.FORECAST_SCALE,
            keys.LATENT,
            keys.PRIOR_LOC,
            keys.PRIOR_SCALE,
            keys.POSTERIOR_LOC,
            keys.POSTERIOR_SCALE,
        ]

    def validate(self, td: TensorDictBase) -> None:
        validate_baseline_batch(td, self.config)

    def posterior(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """PoE posterior ``loc``, ``scale`` ``[B, d_z]``; each expert runs on its present rows only."""
        present = presence(td, self.modalities)
        batch, dz = present.shape[0], self.config.d_latent
        locs, scales = [], []
        for i, spec in enumerate(self.modalities):
            rows = present[:, i].nonzero().squeeze(1)
            # Absent rows: a placeholder expert with unit scale, excluded from the product.
            raw = torch.zeros(batch, 2 * dz, device=present.device)
            if rows.numel():
                expert = self.experts[spec.name](self.encoders[spec.name](td.get(spec.obs_key)[rows]))
                raw = raw.index_copy(0, rows, expert)
            loc, raw_scale = raw.chunk(2, dim=-1)
            locs.append(loc)
            scales.append(F.softplus(raw_scale) + 1e-4)
        return product_of_experts(torch.stack(locs, 1), torch.stack(scales, 1), present)

    def decode(self, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cfg = self.config
        return gaussian_head_output(self.decoder(z), cfg.horizon, cfg.target_dim, cfg.min_scale)

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Writes the forecast and latents; with ``("drop", m)`` masks (``L_mis``) also
        ``("forecast_dropped", ...)``: decoded from the product of the kept experts, with the same noise
        ``ε`` as the full input's ``z`` (the latent is the fusion here, so "the same ``z``" of the paper
        model would make both forecasts equal)."""
        self.validate(td)
        student = student_batch(td, self.modalities)
        both = td if student is None else with_student(td, student)
        loc, scale = self.posterior(both)
        noise = torch.zeros_like(scale[: td.shape[0]])
        if self.training or self.config.eval_latent == "sample":
            noise = torch.randn_like(noise)
        z = loc + scale * noise.repeat(loc.shape[0] // noise.shape[0], 1)
        forecast_loc, forecast_scale = self.decode(z)
        forecast_scale = self.scale_calibration(forecast_scale, presence(both, self.modalities))
        if student is not None:
            (loc, _), (scale, _), (z, _) = loc.chunk(2), scale.chunk(2), z.chunk(2)
            (forecast_loc, dropped_loc), (forecast_scale, dropped_scale) = (
                forecast_loc.chunk(2),
                forecast_scale.chunk(2),
            )
            td.set(keys.FORECAST_DROPPED_LOC, dropped_loc)
            td.set(keys.FORECAST_DROPPED_SCALE, dropped_scale)
        td.set(keys.POSTERIOR_LOC, loc)
        td.set(keys.POSTERIOR_SCALE, scale)
        td.set(keys.PRIOR_LOC, torch.zeros_like(loc))
        td.set(keys.PRIOR_SCALE, torch.ones_like(scale))
        td.set(keys.LATENT, z)
        td.set(keys.FORECAST_LOC, forecast_loc)
        td.set(keys.FORECAST_SCALE, forecast_scale)
        return td

    def sample(self, td: TensorDictBase, num_samples: int = 20) -> TensorDictBase:
        """Write ``("forecast", "samples")`` ``[B, K, T, D]``: decoded means of ``K`` posterior samples.

        Args:
            td (TensorDictBase): a batch following `mmf_rl.keys`; written in place.
            num_samples (int, optional): ``K``. Defaults to ``20``.

        Returns:
            ``td``.
        """
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, found {num_samples}")
        self.validate(td)
        loc, scale = self.posterior(td)
        z = loc.unsqueeze(1) + scale.unsqueeze(1) * torch.randn(
            loc.shape[0], num_samples, loc.shape[1], device=loc.device
        )
        forecast_loc, _ = self.decode(z.flatten(0, 1))
        td.set(keys.FORECAST_SAMPLES, forecast_loc.view(loc.shape[0], num_samples, *forecast_loc.shape[1:]))
        return td
