"""The CVAE evidence lower bound: NLL of the future (under the forecast's distribution) + KL of the
posterior to the prior."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import (
    ForecasterLossBase,
    best_of_k_mse,
    gaussian_kl,
    gaussian_kl_to_standard,
    reduce_batch,
)
from mmf_rl.objectives.config import check_count
from mmf_rl.objectives.distributions import output_distribution_of
from mmf_rl.objectives.registry import register_loss_term


@register_loss_term("elbo")
class ELBOLoss(ForecasterLossBase):
    """``-ELBO = E_q[-log p(y | X, z)] + β KL(q(z | X, y) || p(z | X))`` (paper, "Model Learning").

    The prior is the one the forecaster writes under ``("prior", "loc"/"scale")`` (a learned
    ``p(z | X)``, or ``N(0, I)`` for the paper's standard prior); a model that writes none is
    taken to use ``N(0, I)``. Both terms are summed over their dims (``T × D`` for the NLL,
    ``d_z`` for the KL) and reduced over the batch. The KL is analytic; ``z`` is drawn by the
    forecaster with the reparameterisation trick, one sample per row. ``p(y | X, z)`` is the
    forecaster's output distribution (its config's ``output_distribution``: a Gaussian by default,
    or a Laplace or Student-t with the forecast's loc and scale); the latents stay Gaussian.

    With ``gsnn_weight > 0`` the loss adds Sohn et al.'s (2015) GSNN term ``loss_gsnn = w ·
    E_{p(z|X)}[-log p(y | X, z)]``: :meth:`prepare` asks the forecaster (``"decode_from_prior"``)
    to also decode every row from a prior draw, so training sees the latents used at test time.

    With ``best_of_k_weight > 0`` it adds the best-of-many term of Bhattacharyya et al. (2018)
    (Social-GAN's variety loss): ``loss_best_of_k = w · mean_windows min_k MSE(ŷ_k, y)``, ``ŷ_k`` the
    forecast mean at the ``k``-th of ``K`` draws ``z ~ p(z|X)`` (``"decode_prior_draws"``, one
    decoder call) and the MSE over the ``T × D`` target in its normalised frame, every entry of
    which the NLL scores too (windows with an invalid target step never reach a batch). The
    ELBO never asks the prior's draws to cover the futures while best-of-K metrics (minADE20) score
    exactly that; the min passes the gradient to the best draw only, so the others stay free to
    spread.

    Args:
        forecaster (nn.Module): a :class:`~mmf_rl.models.MultimodalForecaster` (or any module writing the
            same keys).

    Keyword Args:
        kl_weight (float, optional): ``β`` once warm. Defaults to ``1.0``.
        kl_warmup_steps (int, optional): ``β`` grows linearly from ``kl_weight / kl_warmup_steps`` to
            ``kl_weight`` over this many training updates (0, the default: constant). The update count
            is a buffer, so it is saved and restored with the loss's ``state_dict``.
        gsnn_weight (float, optional): ``w`` of the GSNN term (0, the default: no term, no extra decode).
        best_of_k_weight (float, optional): ``w`` of the best-of-K term (0, the default: no term, no extra
            decode).
        best_of_k_samples (int, optional): its ``K`` (>= 1). Defaults to ``20``.
        reduction (str, optional): ``"mean"`` (default) | ``"sum"`` | ``"none"`` over the batch.

    Calling it on a batch returns a TensorDict with ``loss_nll``, ``loss_kl`` (already weighted by
    ``β``), with ``gsnn_weight > 0`` ``loss_gsnn`` (weighted), with ``best_of_k_weight > 0``
    ``loss_best_of_k`` (weighted) and the detached diagnostic ``best_of_k_mse`` (its unweighted mean),
    and the detached diagnostics ``kl`` (unweighted) and ``kl_weight``.

    Raises:
        ValueError: a negative weight or warm-up, ``best_of_k_samples < 1``, or an unknown
            ``reduction``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import ELBOLoss
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> loss = ELBOLoss(model, kl_weight=0.5)
        >>> out = loss(batch)
        >>> sorted(out.keys())
        ['kl', 'kl_weight', 'loss_kl', 'loss_nll']
        >>> sum(value for key, value in out.items() if key.startswith("loss_")).backward()
        >>> sorted(ELBOLoss(model, gsnn_weight=1.0, best_of_k_weight=1.0, best_of_k_samples=4)(batch).keys())
        ['best_of_k_mse', 'kl', 'kl_weight', 'loss_best_of_k', 'loss_gsnn', 'loss_kl', 'loss_nll']
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys the loss reads; ``set_keys(name=key)`` renames one.

        Attributes:
            target (NestedKey): the future ``y``, ``[B, T, D]``. Defaults to ``"target"``.
            forecast_loc (NestedKey): the mean of ``p(y | X, z)`` at the posterior draw, ``[B, T, D]``.
                Defaults to ``("forecast", "loc")``.
            forecast_scale (NestedKey): its standard deviation. Defaults to ``("forecast", "scale")``.
            posterior_loc (NestedKey): the mean of ``q(z | X, y)``, ``[B, d_z]``. Defaults to
                ``("posterior", "loc")``.
            posterior_scale (NestedKey): its standard deviation. Defaults to ``("posterior", "scale")``.
            prior_loc (NestedKey): the mean of ``p(z | X)``, ``[B, d_z]``; absent: ``N(0, I)``.
                Defaults to ``("prior", "loc")``.
            prior_scale (NestedKey): its standard deviation. Defaults to ``("prior", "scale")``.
            from_prior_loc (NestedKey): the mean of the forecast decoded from a prior draw (the GSNN
                term's, read only with ``gsnn_weight > 0``). Defaults to
                ``("forecast_from_prior", "loc")``.
            from_prior_scale (NestedKey): its standard deviation. Defaults to
                ``("forecast_from_prior", "scale")``.
            from_prior_samples (NestedKey): the means of the forecasts decoded from ``K`` prior draws
                (the best-of-K term's, read only with ``best_of_k_weight > 0``), ``[B, K, T, D]``.
                Defaults to ``("forecast_from_prior", "samples")``.
        """

        target: NestedKey = keys.TARGET
        forecast_loc: NestedKey = keys.FORECAST_LOC
        forecast_scale: NestedKey = keys.FORECAST_SCALE
        posterior_loc: NestedKey = keys.POSTERIOR_LOC
        posterior_scale: NestedKey = keys.POSTERIOR_SCALE
        prior_loc: NestedKey = keys.PRIOR_LOC
        prior_scale: NestedKey = keys.PRIOR_SCALE
        from_prior_loc: NestedKey = keys.FORECAST_FROM_PRIOR_LOC
        from_prior_scale: NestedKey = keys.FORECAST_FROM_PRIOR_SCALE
        from_prior_samples: NestedKey = keys.FORECAST_FROM_PRIOR_SAMPLES

    default_keys = _AcceptedKeys
    config_fields = frozenset(
        {"kl_weight", "kl_warmup_steps", "gsnn_weight", "best_of_k_weight", "best_of_k_samples"}
    )

    def __init__(
        self,
        forecaster,
        *,
        kl_weight: float = 1.0,
        kl_warmup_steps: int = 0,
        gsnn_weight: float = 0.0,
        best_of_k_weight: float = 0.0,
        best_of_k_samples: int = 20,
        reduction: str = "mean",
    ):
        super().__init__(forecaster, reduction)
        if kl_weight < 0 or kl_warmup_steps < 0:
            raise ValueError(
                f"kl_weight and kl_warmup_steps must be >= 0, found {kl_weight}, {kl_warmup_steps}"
            )
        if gsnn_weight < 0:
            raise ValueError(f"gsnn_weight must be >= 0, found {gsnn_weight}")
        if best_of_k_weight < 0:
            raise ValueError(f"best_of_k_weight must be >= 0, found {best_of_k_weight}")
        check_count(best_of_k_samples, "best_of_k_samples")
        self.kl_weight = kl_weight
        self.kl_warmup_steps = kl_warmup_steps
        self.gsnn_weight = gsnn_weight
        self.best_of_k_weight = best_of_k_weight
        self.best_of_k_samples = best_of_k_samples
        self.output_distribution = output_distribution_of(forecaster)
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))

    @classmethod
    def from_config(cls, forecaster, loss_cfg) -> ELBOLoss:
        """``kl_weight``, ``kl_warmup_steps``, ``gsnn_weight`` and ``best_of_k_*`` of the loss config; a
        model that declares ``decodes_from_prior = False`` refuses the GSNN and best-of-K terms rather
        than fail mid-training."""
        for option in ("gsnn_weight", "best_of_k_weight"):
            if getattr(loss_cfg, option) > 0 and not getattr(forecaster, "decodes_from_prior", True):
                raise ValueError(
                    f"loss.{option} > 0 needs a model that decodes from its prior in training "
                    f"(model=forecaster); {type(forecaster).__name__} does not: set loss.{option}=0"
                )
        return cls(
            forecaster,
            kl_weight=loss_cfg.kl_weight,
            kl_warmup_steps=loss_cfg.kl_warmup_steps,
            gsnn_weight=loss_cfg.gsnn_weight,
            best_of_k_weight=loss_cfg.best_of_k_weight,
            best_of_k_samples=loss_cfg.best_of_k_samples,
        )

    @classmethod
    def unread_settings(cls, loss_cfg, model_settings) -> dict[str, str]:
        """The warm-up scales ``β``, which ``kl_weight=0`` leaves at 0; ``K`` is the best-of-K term's,
        which ``best_of_k_weight=0`` turns off."""
        conditional = {"kl_warmup_steps": "kl_weight", "best_of_k_samples": "best_of_k_weight"}
        return {
            setting: f"only with loss.{weight} > 0 (found {getattr(loss_cfg, weight)})"
            for setting, weight in conditional.items()
            if not getattr(loss_cfg, weight)
        }

    def _loss_in_keys(self) -> list:
        k = self.tensor_keys
        extra = [k.from_prior_loc, k.from_prior_scale] if self.gsnn_weight else []
        extra += [k.from_prior_samples] if self.best_of_k_weight else []
        return [
            k.target,
            k.forecast_loc,
            k.forecast_scale,
            k.posterior_loc,
            k.posterior_scale,
            k.prior_loc,
            k.prior_scale,
            *extra,
        ]

    @property
    def out_keys(self):
        gsnn = ["loss_gsnn"] if self.gsnn_weight else []
        best_of_k = ["loss_best_of_k", "best_of_k_mse"] if self.best_of_k_weight else []
        return ["loss_nll", "loss_kl", *gsnn, *best_of_k, "kl", "kl_weight"]

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        if self.gsnn_weight:
            td.set(keys.DECODE_FROM_PRIOR, torch.ones(td.batch_size, dtype=torch.bool, device=td.device))
        if self.best_of_k_weight:
            draws = (*td.batch_size, self.best_of_k_samples)
            td.set(keys.DECODE_PRIOR_DRAWS, torch.ones(draws, dtype=torch.bool, device=td.device))
        return td

    def current_kl_weight(self) -> float:
        """``β`` at the current update count (``kl_weight`` once the warm-up is over)."""
        if not self.kl_warmup_steps:
            return self.kl_weight
        return self.kl_weight * min(1.0, (int(self.num_updates) + 1) / self.kl_warmup_steps)

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        target = self._get(td, k.target)
        nll = (
            self.output_distribution.nll(
                target, self._get(td, k.forecast_loc), self._get(td, k.forecast_scale)
            )
            .flatten(1)
            .sum(-1)
        )
        post_loc, post_scale = self._get(td, k.posterior_loc), self._get(td, k.posterior_scale)
        prior_loc, prior_scale = td.get(k.prior_loc, None), td.get(k.prior_scale, None)
        if prior_loc is None or prior_scale is None:
            kl = gaussian_kl_to_standard(post_loc, post_scale).sum(-1)
        else:
            kl = gaussian_kl(post_loc, post_scale, prior_loc, prior_scale).sum(-1)
        beta = self.current_kl_weight()
        if self.training and torch.is_grad_enabled():
            self.num_updates += 1
        out = TensorDict(
            loss_nll=reduce_batch(nll, self.reduction),
            loss_kl=beta * reduce_batch(kl, self.reduction),
            kl=kl.mean().detach(),
            kl_weight=torch.tensor(beta),
        )
        out.update(self._prior_draw_terms(td, target))
        return out

    def _prior_draw_terms(self, td: TensorDictBase, target: torch.Tensor) -> dict:
        """The terms scored on forecasts decoded from prior draws, those switched on: GSNN, best-of-K."""
        k, terms = self.tensor_keys, {}
        if self.gsnn_weight:
            loc, scale = self._get(td, k.from_prior_loc), self._get(td, k.from_prior_scale)
            gsnn = self.output_distribution.nll(target, loc, scale)
            terms["loss_gsnn"] = self.gsnn_weight * reduce_batch(gsnn.flatten(1).sum(-1), self.reduction)
        if self.best_of_k_weight:
            best = best_of_k_mse(target, self._get(td, k.from_prior_samples))
            terms["loss_best_of_k"] = self.best_of_k_weight * reduce_batch(best, self.reduction)
            terms["best_of_k_mse"] = best.mean().detach()
        return terms
