"""The paper's missing-modality loss ``L_mis``: the forecast should not change when a modality is lost."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey

from mmf_rl import keys
from mmf_rl.objectives.common import ForecasterLossBase, gaussian_kl, reduce_batch


class MissingModalityLoss(ForecasterLossBase):
    """``L_mis = KL(p(y | X, z) || p(y | X \\ {m}, z))`` with one present modality ``m`` dropped.

    :meth:`prepare` picks, per sample with at least two present modalities, one of them
    uniformly at random (global torch RNG, so seeded runs repeat) and writes the ``("drop", m)``
    masks; the forecaster then decodes the teacher (all present modalities) and the student
    (``m`` removed) with the same ``z`` in one batched pass. Samples with a single present
    modality have nothing to drop and are left out of the average.

    Args:
        forecaster: a :class:`~mmf_rl.models.MultimodalForecaster`.
        weight: multiplies ``loss_mis``.
        detach_teacher: stop the gradient through the teacher's Gaussian (default). The paper
            trains both sides jointly and calls the full-modality side the teacher without saying
            whether it is detached; detaching keeps ``L_mis`` from pulling the full-modality
            forecast toward the degraded one, which only the ELBO should shape.
        reduction: ``"mean"`` (over eligible samples) | ``"sum"`` | ``"none"`` (per sample, 0
            where nothing was dropped).

    Returns ``loss_mis`` (weighted) and the detached diagnostics ``mis_kl`` (unweighted) and
    ``mis_fraction`` (share of samples that had a modality dropped).

    Keys: ``present`` maps each of the forecaster's modalities to the mask :meth:`prepare` picks
    the dropped modality from (default ``("present", m)``, resolved from the forecaster's
    modalities). ``set_keys(present={"image": "image_may_drop"})`` points some of them elsewhere,
    e.g. to limit ``L_mis`` to the sensors that can fail; such a mask must be False wherever the
    modality is absent. The ``("drop", m)`` masks it writes are the forecaster's input, so their
    names are the contract's.
    """

    @dataclass
    class _AcceptedKeys:
        forecast_loc: NestedKey = keys.FORECAST_LOC
        forecast_scale: NestedKey = keys.FORECAST_SCALE
        dropped_loc: NestedKey = keys.FORECAST_DROPPED_LOC
        dropped_scale: NestedKey = keys.FORECAST_DROPPED_SCALE
        present: dict[str, NestedKey] = field(default_factory=dict)

    default_keys = _AcceptedKeys
    out_keys = ["loss_mis", "mis_kl", "mis_fraction"]

    def __init__(self, forecaster, *, weight: float = 1.0, detach_teacher: bool = True, reduction: str = "mean"):
        super().__init__(forecaster, reduction)
        if weight < 0:
            raise ValueError(f"weight must be >= 0, found {weight}")
        self.weight = weight
        self.detach_teacher = detach_teacher
        self.modality_names = [spec.name for spec in forecaster.modalities]

    def default_tensor_keys(self) -> _AcceptedKeys:
        return self.default_keys(present={spec.name: spec.present_key for spec in self.forecaster.modalities})

    def set_keys(self, **kwargs) -> None:
        present = kwargs.get("present")
        if present is not None:
            unknown = sorted(set(present) - set(self.modality_names))
            if unknown:
                raise ValueError(f"{type(self).__name__}.set_keys(present=...): {unknown} are not modalities "
                                 f"of the forecaster; expected a subset of {self.modality_names}")
            kwargs["present"] = {**self.tensor_keys.present, **present}
        super().set_keys(**kwargs)

    def _loss_in_keys(self) -> list:
        k = self.tensor_keys
        return [k.forecast_loc, k.forecast_scale, k.dropped_loc, k.dropped_scale, *k.present.values()] + [
            keys.drop_key(m) for m in self.modality_names
        ]

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        present = torch.stack([td.get(self.tensor_keys.present[m]) for m in self.modality_names], dim=1)
        # argmax of uniform scores over the present modalities = one of them uniformly at random.
        scores = torch.rand(present.shape, device=present.device).masked_fill(~present, -1.0)
        choice = torch.nn.functional.one_hot(scores.argmax(1), len(self.modality_names)).bool()
        drop = choice & (present.sum(1, keepdim=True) >= 2)
        for i, name in enumerate(self.modality_names):
            td.set(keys.drop_key(name), drop[:, i])
        return td

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        k = self.tensor_keys
        teacher_loc, teacher_scale = self._get(td, k.forecast_loc), self._get(td, k.forecast_scale)
        if self.detach_teacher:
            teacher_loc, teacher_scale = teacher_loc.detach(), teacher_scale.detach()
        kl = gaussian_kl(teacher_loc, teacher_scale, self._get(td, k.dropped_loc), self._get(td, k.dropped_scale))
        kl = kl.flatten(1).sum(-1)
        eligible = torch.stack([self._get(td, keys.drop_key(m)) for m in self.modality_names], dim=1).any(1)
        kl = kl * eligible
        if self.reduction == "mean":
            loss = kl.sum() / eligible.sum().clamp_min(1)
        else:
            loss = reduce_batch(kl, self.reduction)
        return TensorDict(
            loss_mis=self.weight * loss,
            mis_kl=(kl.sum() / eligible.sum().clamp_min(1)).detach(),
            mis_fraction=eligible.float().mean(),
        )
