"""The paper's missing-modality loss ``L_mis``: the forecast should not change when modalities are lost."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import (
    ForecasterLossBase,
    gaussian_kl,
    has_learned_prior,
    model_settings_of,
    reduce_batch,
)
from mmf_rl.objectives.config import STEP_CUTS
from mmf_rl.objectives.distributions import output_distribution_of
from mmf_rl.objectives.registry import register_loss_term


@register_loss_term("mis")
class MissingModalityLoss(ForecasterLossBase):
    """``L_mis = KL(p(y | X, z) || p(y | X \\ S, z))`` with a random set ``S`` of present modalities dropped.

    :meth:`prepare` picks, per sample with at least two present modalities, how many to drop
    (``k`` uniform in ``1..min(max_dropped, M_i - 1)``, ``M_i`` the sample's present modalities),
    then which (a uniformly random ``k``-subset of the present ones; global torch RNG, so seeded
    runs repeat), and writes the ``("drop", m)`` masks; the forecaster then decodes the teacher
    (all present modalities) and the student (``S`` removed) with the same ``z`` in one batched
    pass. Samples with a single present modality have nothing to drop and are left out of the
    average. ``max_dropped=1`` (the default) is the paper's setting: exactly one modality;
    ``max_dropped=None`` lets any sample be reduced to a single modality, so single-modality
    inputs are trained.

    ``p(y | ·, z)`` is the forecaster's output distribution (its config's ``output_distribution``,
    :func:`~mmf_rl.objectives.output_distribution_of`): the KL between two Gaussians by default, between
    two Laplace distributions in closed form, between two Student-t distributions by quadrature
    (:class:`~mmf_rl.objectives.StudentTOutput`).

    **Tail cuts** (``step_drop_prob > 0``, not in the paper): a sensor that dies part-way through a
    window leaves its last steps absent. With probability ``step_drop_prob`` a sample's drop is a
    tail cut instead: one of its present windowed (image or sequence) modalities, uniformly among
    those with at least two present steps, loses its last ``k`` present steps for the student
    (``k`` uniform in ``1..min(max_dropped_steps, n - 1)``, ``n`` its present steps: ``1..H-1`` for
    a full window), so the student still holds it for at least one step. The cut is written as
    ``("drop_steps", m)`` ``[B, H]`` masks (True: a step the student loses) beside all-False
    ``("drop", m)``; the forecaster removes those steps from the student's ``("present_steps", m)``
    only (the teacher sees everything). A sample with a single present modality can get a tail cut
    (the modality stays present); a sample drawn for one with no modality to cut gets the whole
    drop it would have had. ``step_drop_prob=0`` (the default) writes no ``("drop_steps", m)`` and
    draws nothing more from the RNG: the paper's ``L_mis`` exactly. ``step_cut="burst"`` cuts ``k``
    consecutive present steps starting at a uniformly random one of the ``n - k + 1`` places instead
    of the last ``k``: a sensor that drops out and comes back leaves gaps inside the window, which
    tail cuts never show the student.

    With a learned prior (``ForecasterConfig.prior="learned"``) the forecaster also computes the
    prior of the degraded input from the fusion of the kept modalities, and ``loss_mis_prior =
    prior_weight · KL(p(z | X) || p(z | X \\ S))`` ties it to the full input's prior (teacher
    detached like the forecast's).

    Args:
        forecaster (nn.Module): a :class:`~mmf_rl.models.MultimodalForecaster`.

    Keyword Args:
        weight (float, optional): multiplies ``loss_mis``. Defaults to ``1.0``.
        detach_teacher (bool, optional): stop the gradient through the teacher's side (the full-input forecast
            and, with a learned prior, the full-input prior). The default trains both sides jointly, as the
            paper does: ``L_mis`` then also pulls the full-input forecast toward what the kept modalities can
            support, which measured more accurate with every sensor as well as without one (docs/results.md).
            Detaching leaves the full-input forecast to the ELBO.
        max_dropped (int, optional): the most modalities dropped from one sample (``>= 1``; default ``1``),
            ``None``: no cap (up to ``M_i - 1``).
        dropped_nll_weight (float, optional): weight of ``loss_mis_nll``, the NLL of the target under the
            degraded forecast (0, the default: no such term).
        prior_weight (float, optional): weight of ``loss_mis_prior`` (used only with a learned prior).
            Defaults to ``1.0``.
        step_drop_prob (float, optional): probability (in ``[0, 1]``) that a sample's drop is a tail cut of
            one windowed modality instead of whole modalities (0, the default: never).
        max_dropped_steps (int, optional): the most steps a tail cut removes (``>= 1``); ``None``: up to all
            but one of the modality's present steps.
        step_cut (str, optional): ``"tail"`` (the default: the last present steps) or ``"burst"`` (a run of
            consecutive present steps anywhere in the window), `STEP_CUTS`.
        reduction (str, optional): ``"mean"`` (over eligible samples) | ``"sum"`` | ``"none"`` (per sample, 0
            where nothing was dropped).

    Calling it on a batch returns ``loss_mis`` (weighted), ``loss_mis_nll`` and ``loss_mis_prior`` when
    they apply, and the detached diagnostics ``mis_kl`` (unweighted), ``mis_fraction`` (share of samples
    that had a modality or steps dropped), ``mis_dropped`` (mean number of whole modalities dropped over
    the samples that had some) and, with tail cuts, ``mis_tail_fraction`` (share of samples cut).

    Raises:
        ValueError: a negative weight, ``max_dropped`` or ``max_dropped_steps`` below 1,
            ``step_drop_prob`` outside ``[0, 1]`` (or above 0 for a model without a windowed modality),
            an unknown ``step_cut`` or ``reduction``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import MissingModalityLoss
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> loss = MissingModalityLoss(model, weight=1.0)
        >>> out = loss(batch)
        >>> sorted(out.keys())
        ['loss_mis', 'mis_dropped', 'mis_fraction', 'mis_kl']
        >>> out["mis_fraction"]  # every sample has two modalities: one was dropped from each
        tensor(1.)
        >>> out["loss_mis"].backward()
    """

    @dataclass
    class _AcceptedKeys:
        """The tensordict keys the loss reads; ``set_keys(name=key)`` renames one.

        Attributes:
            target (NestedKey): the future ``y``, ``[B, T, D]`` (read for ``loss_mis_nll``).
                Defaults to ``"target"``.
            forecast_loc (NestedKey): the teacher's forecast mean (all present modalities),
                ``[B, T, D]``. Defaults to ``("forecast", "loc")``.
            forecast_scale (NestedKey): its standard deviation. Defaults to ``("forecast", "scale")``.
            dropped_loc (NestedKey): the student's forecast mean (``S`` removed, same ``z``).
                Defaults to ``("forecast_dropped", "loc")``.
            dropped_scale (NestedKey): its standard deviation. Defaults to
                ``("forecast_dropped", "scale")``.
            present (dict[str, NestedKey]): for each of the forecaster's modalities, the mask
                :meth:`prepare` picks the dropped modalities from. Defaults to ``("present", m)``,
                resolved from the forecaster's modalities; ``set_keys(present={"image":
                "image_may_drop"})`` points some elsewhere, e.g. to limit ``L_mis`` to the sensors
                that can fail (such a mask must be False wherever the modality is absent). The
                ``("drop", m)`` masks it writes are the forecaster's input: their names are the
                contract's, not keys of the loss.
            prior_loc (NestedKey): the learned prior's mean of the full input, ``[B, d_z]`` (read
                for ``loss_mis_prior``). Defaults to ``("prior", "loc")``.
            prior_scale (NestedKey): its standard deviation. Defaults to ``("prior", "scale")``.
            prior_dropped_loc (NestedKey): the learned prior's mean of the degraded input. Defaults
                to ``("prior_dropped", "loc")``.
            prior_dropped_scale (NestedKey): its standard deviation. Defaults to
                ``("prior_dropped", "scale")``.
        """

        target: NestedKey = keys.TARGET
        forecast_loc: NestedKey = keys.FORECAST_LOC
        forecast_scale: NestedKey = keys.FORECAST_SCALE
        dropped_loc: NestedKey = keys.FORECAST_DROPPED_LOC
        dropped_scale: NestedKey = keys.FORECAST_DROPPED_SCALE
        present: dict[str, NestedKey] = field(default_factory=dict)
        prior_loc: NestedKey = keys.PRIOR_LOC
        prior_scale: NestedKey = keys.PRIOR_SCALE
        prior_dropped_loc: NestedKey = keys.PRIOR_DROPPED_LOC
        prior_dropped_scale: NestedKey = keys.PRIOR_DROPPED_SCALE

    default_keys = _AcceptedKeys
    config_fields = frozenset(
        {
            "missing_modality_weight",
            "detach_teacher",
            "max_dropped",
            "dropped_nll_weight",
            "dropped_prior_weight",
            "step_drop_prob",
            "max_dropped_steps",
            "step_cut",
        }
    )

    def __init__(
        self,
        forecaster,
        *,
        weight: float = 1.0,
        detach_teacher: bool = False,
        max_dropped: int | None = 1,
        dropped_nll_weight: float = 0.0,
        prior_weight: float = 1.0,
        step_drop_prob: float = 0.0,
        max_dropped_steps: int | None = None,
        step_cut: str = "tail",
        reduction: str = "mean",
    ):
        super().__init__(forecaster, reduction)
        for name, value in (
            ("weight", weight),
            ("dropped_nll_weight", dropped_nll_weight),
            ("prior_weight", prior_weight),
        ):
            if value < 0:
                raise ValueError(f"{name} must be >= 0, found {value}")
        if max_dropped is not None and max_dropped < 1:
            raise ValueError(
                f"max_dropped must be >= 1 (or None: up to all but one modality), found {max_dropped}"
            )
        if not 0.0 <= step_drop_prob <= 1.0:
            raise ValueError(
                f"step_drop_prob must be in [0, 1] (the probability that a sample's drop is a tail cut), "
                f"found {step_drop_prob}"
            )
        if max_dropped_steps is not None and max_dropped_steps < 1:
            raise ValueError(
                f"max_dropped_steps must be >= 1 (or None: up to all but one present step), "
                f"found {max_dropped_steps}"
            )
        if step_cut not in STEP_CUTS:
            raise ValueError(
                f"step_cut must be one of {list(STEP_CUTS)} (where a cut's steps fall), found {step_cut!r}"
            )
        self.windowed = [spec.name for spec in forecaster.modalities if spec.kind != "vector"]
        if step_drop_prob > 0 and not self.windowed:
            raise ValueError(
                "step_drop_prob > 0 cuts the last steps of a windowed (image or sequence) modality, and "
                "this forecaster has none; set step_drop_prob=0"
            )
        self.step_drop_prob = step_drop_prob
        self.max_dropped_steps = max_dropped_steps
        self.step_cut = step_cut
        self.weight = weight
        self.detach_teacher = detach_teacher
        self.max_dropped = max_dropped
        self.dropped_nll_weight = dropped_nll_weight
        # Only a learned prior depends on the present modalities; N(0, I) has nothing to tie.
        self.prior_weight = prior_weight if has_learned_prior(model_settings_of(forecaster)) else 0.0
        self.modality_names = [spec.name for spec in forecaster.modalities]
        self.output_distribution = output_distribution_of(forecaster)

    @classmethod
    def from_config(cls, forecaster, loss_cfg) -> MissingModalityLoss | None:
        """The loss config's ``missing_modality_weight`` and ``L_mis`` options; weight 0 turns the
        term off (the paper's ablation, ``loss=no_mis``)."""
        if loss_cfg.missing_modality_weight <= 0:
            return None
        return cls(
            forecaster,
            weight=loss_cfg.missing_modality_weight,
            detach_teacher=loss_cfg.detach_teacher,
            max_dropped=loss_cfg.max_dropped,
            dropped_nll_weight=loss_cfg.dropped_nll_weight,
            prior_weight=loss_cfg.dropped_prior_weight,
            step_drop_prob=loss_cfg.step_drop_prob,
            max_dropped_steps=loss_cfg.max_dropped_steps,
            step_cut=loss_cfg.step_cut,
        )

    @classmethod
    def unread_settings(cls, loss_cfg, model_settings) -> dict[str, str]:
        """Weight 0 turns the term off (:meth:`from_config`), leaving every other setting unread; on, the
        prior tie needs a learned prior and the tail cuts' length a tail cut."""
        weight = loss_cfg.missing_modality_weight
        if weight <= 0:
            off = f"only with loss.missing_modality_weight > 0 (found {weight}, which turns it off)"
            return dict.fromkeys(sorted(cls.config_fields - {"missing_modality_weight"}), off)
        unread = {}
        if not has_learned_prior(model_settings):
            unread["dropped_prior_weight"] = (
                "only with a learned prior (model.prior=learned), which this model does not have"
            )
        if not (step_drop_prob := loss_cfg.step_drop_prob):
            for name in ("max_dropped_steps", "step_cut"):
                unread[name] = f"only with loss.step_drop_prob > 0 (found {step_drop_prob})"
        return unread

    def default_tensor_keys(self) -> _AcceptedKeys:
        return self.default_keys(present={spec.name: spec.present_key for spec in self.forecaster.modalities})

    def set_keys(self, **kwargs) -> None:
        present = kwargs.get("present")
        if present is not None:
            unknown = sorted(set(present) - set(self.modality_names))
            if unknown:
                raise ValueError(
                    f"{type(self).__name__}.set_keys(present=...): {unknown} are not modalities "
                    f"of the forecaster; expected a subset of {self.modality_names}"
                )
            kwargs["present"] = {**self.tensor_keys.present, **present}
        super().set_keys(**kwargs)

    def _loss_in_keys(self) -> list:
        k = self.tensor_keys
        extra = [k.target] if self.dropped_nll_weight else []
        if self.prior_weight:
            extra += [k.prior_loc, k.prior_scale, k.prior_dropped_loc, k.prior_dropped_scale]
        return (
            [
                k.forecast_loc,
                k.forecast_scale,
                k.dropped_loc,
                k.dropped_scale,
                *k.present.values(),
                *extra,
            ]
            + [keys.drop_key(m) for m in self.modality_names]
            + self._drop_steps_keys()
        )

    def _drop_steps_keys(self) -> list:
        return [keys.drop_steps_key(m) for m in self.windowed] if self.step_drop_prob else []

    @property
    def out_keys(self):
        terms = (
            ["loss_mis"]
            + (["loss_mis_nll"] if self.dropped_nll_weight else [])
            + (["loss_mis_prior"] if self.prior_weight else [])
        )
        return (
            terms
            + ["mis_kl", "mis_fraction", "mis_dropped"]
            + (["mis_tail_fraction"] if self.step_drop_prob else [])
        )

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        present = torch.stack([td.get(self.tensor_keys.present[m]) for m in self.modality_names], dim=1)
        count = present.sum(1)
        droppable = (count - 1).clamp_min(0)
        if self.max_dropped is not None:
            droppable = droppable.clamp_max(self.max_dropped)
        # Uniform scores over the present modalities (absent ones last): the k top-ranked are a
        # uniformly random k-subset of the present ones.
        scores = torch.rand(present.shape, device=present.device).masked_fill(~present, -1.0)
        if self.max_dropped == 1:  # k = 1 where possible (the paper's setting): no draw for k
            number = droppable
        else:
            number = (torch.rand(count.shape, device=present.device) * droppable).long() + 1
            number = number * (droppable > 0)
        rank = scores.argsort(1, descending=True).argsort(1)
        drop = present & (rank < number.unsqueeze(1))
        if self.step_drop_prob:
            cut = self._step_cuts(td, present)
            drop &= ~cut.flatten(1).any(1, keepdim=True)  # a tail cut instead of the whole drop
            for i, name in enumerate(self.windowed):
                td.set(keys.drop_steps_key(name), cut[:, i])
        for i, name in enumerate(self.modality_names):
            td.set(keys.drop_key(name), drop[:, i])
        return td

    def _step_cuts(self, td: TensorDictBase, present: torch.Tensor) -> torch.Tensor:
        """The steps each sample's student loses, ``[B, W, H]`` for the ``W`` windowed modalities:
        with probability ``step_drop_prob``, ``k`` consecutive present steps of one of them, the last
        ones or (``step_cut="burst"``) from a uniformly random start."""
        windowed_present = present[:, [self.modality_names.index(m) for m in self.windowed]]
        steps = torch.stack(
            [self._present_steps(td, m, windowed_present[:, i]) for i, m in enumerate(self.windowed)], 1
        )
        count = steps.sum(-1)  # [B, W]
        cuttable = count >= 2  # a cut keeps one present step at least
        chosen = torch.rand(cuttable.shape, device=steps.device).masked_fill(~cuttable, -1.0).argmax(1)
        cut_row = (torch.rand(count.shape[0], device=steps.device) < self.step_drop_prob) & cuttable.any(1)
        chosen_count = count.gather(1, chosen.unsqueeze(1)).squeeze(1)  # n, the cut modality's steps
        most = chosen_count - 1
        if self.max_dropped_steps is not None:
            most = most.clamp_max(self.max_dropped_steps)
        length = (torch.rand(most.shape, device=steps.device) * most).long() + 1
        # Present steps numbered from 0 at the window's end: a cut is the run numbered
        # [offset, offset + k); the tail's offset is 0, a burst's uniform in 0..n - k.
        from_end = steps.flip(-1).cumsum(-1).flip(-1) - 1
        offset = torch.zeros_like(length)
        if self.step_cut == "burst":
            places = chosen_count - length + 1
            offset = (torch.rand(places.shape, device=steps.device) * places.clamp_min(1)).long()
        run = (from_end >= offset.view(-1, 1, 1)) & (from_end < (offset + length).view(-1, 1, 1))
        picked = F.one_hot(chosen, len(self.windowed)).bool() & cut_row.unsqueeze(1)
        return steps & run & picked.unsqueeze(-1)

    def _present_steps(self, td: TensorDictBase, modality: str, present: torch.Tensor) -> torch.Tensor:
        """``[B, H]``: the steps where ``modality`` is present (every step of a present window without
        ``("present_steps", m)``)."""
        steps = td.get(keys.present_steps_key(modality), None)
        if steps is None:
            steps = torch.ones(
                td.get(keys.obs_key(modality)).shape[:2], dtype=torch.bool, device=present.device
            )
        return steps & present.unsqueeze(1)

    def _per_eligible(self, per_sample: torch.Tensor, eligible: torch.Tensor) -> torch.Tensor:
        per_sample = per_sample * eligible
        if self.reduction == "mean":
            return per_sample.sum() / eligible.sum().clamp_min(1)
        return reduce_batch(per_sample, self.reduction)

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        teacher_loc, teacher_scale = self._get(td, k.forecast_loc), self._get(td, k.forecast_scale)
        if self.detach_teacher:
            teacher_loc, teacher_scale = teacher_loc.detach(), teacher_scale.detach()
        student_loc, student_scale = self._get(td, k.dropped_loc), self._get(td, k.dropped_scale)
        kl = self.output_distribution.kl(teacher_loc, teacher_scale, student_loc, student_scale)
        kl = kl.flatten(1).sum(-1)
        dropped = torch.stack([self._get(td, keys.drop_key(m)) for m in self.modality_names], dim=1)
        cut = torch.zeros_like(dropped[:, 0])  # samples whose student lost steps (tail cuts)
        for key in self._drop_steps_keys():
            cut = cut | self._get(td, key).any(1)
        eligible = dropped.any(1) | cut
        loss = self._per_eligible(kl, eligible)
        out = TensorDict(loss_mis=self.weight * loss)
        if self.dropped_nll_weight:
            nll = self.output_distribution.nll(self._get(td, k.target), student_loc, student_scale)
            nll = nll.flatten(1).sum(-1)
            out.set("loss_mis_nll", self.dropped_nll_weight * self._per_eligible(nll, eligible))
        if self.prior_weight:
            prior_loc, prior_scale = self._get(td, k.prior_loc), self._get(td, k.prior_scale)
            if self.detach_teacher:
                prior_loc, prior_scale = prior_loc.detach(), prior_scale.detach()
            prior_kl = gaussian_kl(
                prior_loc,
                prior_scale,
                self._get(td, k.prior_dropped_loc),
                self._get(td, k.prior_dropped_scale),
            ).sum(-1)
            out.set("loss_mis_prior", self.prior_weight * self._per_eligible(prior_kl, eligible))
        out.update(
            mis_kl=(kl * eligible).sum().detach() / eligible.sum().clamp_min(1),
            mis_fraction=eligible.float().mean(),
            mis_dropped=dropped.sum(1).float().sum() / dropped.any(1).sum().clamp_min(1),
        )
        if self.step_drop_prob:
            out.set("mis_tail_fraction", cut.float().mean())
        return out
