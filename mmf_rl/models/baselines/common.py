"""What the baselines share: their configuration, the zero-fill protocol, per-step tokenizers, the
``L_mis`` student pass.

Every baseline follows the batch contract of :mod:`mmf_rl.keys`: it reads ``("obs", m)`` and
``("present", m)`` and writes ``("forecast", "loc"/"scale")`` ``[B, T, D]``, the location and scale of
its output distribution (``output_distribution``: a diagonal Gaussian by default), whose scale is
multiplied in eval mode by its presence pattern's factor (``scale_calibration``,
:mod:`mmf_rl.models.scale_calibration`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from functools import partial
from typing import ClassVar

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from mmf_rl import keys
from mmf_rl.configuration import SavedConfigMixin
from mmf_rl.keys import NONFINITE_RULES, ModalitySpec, NonFiniteRule
from mmf_rl.models.encoders import ImageWindowEncoder, check_encoder, with_encoder_kwargs
from mmf_rl.models.hub import PretrainedModel
from mmf_rl.models.scale_calibration import PresenceScaleCalibration
from mmf_rl.objectives.distributions import (
    DEFAULT_OUTPUT_DF,
    DEFAULT_OUTPUT_DISTRIBUTION,
    output_distribution_of,
)


@dataclass
class BaselineConfig(SavedConfigMixin):
    """Sizes shared by every baseline; each baseline's config adds its own fields.

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

    Raises:
        ValueError: no modality, duplicate names, an unknown encoder, a size below 1, ``min_scale <= 0``,
            an unknown ``nonfinite`` or ``output_distribution``, or ``output_df <= 2`` with ``"student_t"``
            (the message names the config class and field).
    """

    modalities: list[ModalitySpec] = field(default_factory=list)
    history: int = 10
    horizon: int = 10
    target_dim: int = 2
    d_model: int = 64
    head_hidden: int = 256
    min_scale: float = 1e-3
    nonfinite: NonFiniteRule = "raise"
    output_distribution: str = DEFAULT_OUTPUT_DISTRIBUTION
    output_df: float = DEFAULT_OUTPUT_DF
    # What a config saved before a setting existed read as (to_dict writes every setting: a saved config
    # lacks one only if older): the model of its time, whatever the default becomes.
    SAVED_BEFORE: ClassVar[dict[str, object]] = {"output_distribution": "normal"}

    def __post_init__(self):
        self.modalities = [
            m if isinstance(m, ModalitySpec) else ModalitySpec.from_dict(m) for m in self.modalities
        ]
        name = type(self).__name__
        if not self.modalities:
            raise ValueError(f"{name}.modalities is empty: the model needs at least one modality")
        names = [m.name for m in self.modalities]
        if len(set(names)) != len(names):
            raise ValueError(f"{name}.modalities: duplicate names in {names}")
        # An unknown encoder is an error even for a baseline that tokenizes per step instead.
        for spec in self.modalities:
            check_encoder(spec.name, spec.encoder, spec.kind)
        if self.nonfinite not in NONFINITE_RULES:
            raise ValueError(f"{name}.nonfinite must be one of {NONFINITE_RULES}, found {self.nonfinite!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type in ("int", int) and (not isinstance(value, int) or value < 1):
                raise ValueError(f"{name}.{f.name} must be an integer >= 1, found {value!r}")
        if not self.min_scale > 0:
            raise ValueError(
                f"{name}.min_scale must be > 0 (the floor of every forecast scale), found {self.min_scale!r}"
            )
        try:
            output_distribution_of(self)
        except ValueError as error:
            raise ValueError(f"{name}: {error}") from None

    def to_dict(self) -> dict:
        """The config as plain data (modalities as dicts), what :meth:`from_dict` reads back."""
        d = asdict(self)
        d["modalities"] = [m.to_dict() for m in self.modalities]
        return d


def zero_filled(td: TensorDictBase, spec: ModalitySpec) -> torch.Tensor:
    """``("obs", m)`` with absent samples replaced by zeros: the zero-fill protocol.

    A baseline that cannot represent absence sees a missing sensor as an all-zero signal: for
    vectors zero is the training mean (they are normalised), for images an all-black window
    (what a dead camera delivers). ``torch.where`` rather than a product, so a NaN stored under an
    absent modality cannot leak through ``0 * NaN``.
    """
    obs = td.get(spec.obs_key)
    present = td.get(spec.present_key).view(-1, *[1] * (obs.dim() - 1))
    return torch.where(present, obs, torch.zeros((), dtype=obs.dtype, device=obs.device))


class StepTokenizer(nn.Module):
    """One modality's window -> one ``d``-token per step ``[N, L, d]``.

    Images: the forecaster's ConvNet applied to each frame separately (``L = H``; the spec's
    ``encoder_kwargs`` set its channels). Sequences: a linear layer + ReLU per step (``L = H``).
    Single vectors: the same, as a one-step sequence (``L = 1``).
    """

    def __init__(self, spec: ModalitySpec, d_model: int):
        super().__init__()
        self.kind = spec.kind
        if spec.kind == "image":
            per_frame = partial(ImageWindowEncoder, spec, 1, d_model, temporal="stack")
            self.frame = with_encoder_kwargs(spec, per_frame, "the baselines' per-frame ConvNet")
        else:
            self.frame = nn.Sequential(nn.Linear(spec.shape[0], d_model), nn.ReLU())

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if self.kind == "image":
            n, steps = obs.shape[:2]
            return self.frame(obs.flatten(0, 1).unsqueeze(1)).view(n, steps, -1)
        if self.kind == "vector":
            obs = obs.unsqueeze(1)
        return self.frame(obs)


def presence(td: TensorDictBase, modalities: list[ModalitySpec]) -> torch.Tensor:
    """``[B, M]`` bool: ``("present", m)`` of each modality, in spec order."""
    return torch.stack([td.get(s.present_key) for s in modalities], dim=1)


def validate_baseline_batch(td: TensorDictBase, config: BaselineConfig) -> None:
    """Raise a clear error if ``td`` does not follow the key contract for ``config``'s sizes; with
    ``nonfinite="absent"``, mark its present samples holding NaN/Inf absent in ``td``."""
    keys.validate_batch(
        td, config.modalities, config.history, config.horizon, config.target_dim, nonfinite=config.nonfinite
    )
    if config.nonfinite == "absent":
        keys.mark_nonfinite_absent(td, config.modalities)


def gaussian_head_output(raw: torch.Tensor, horizon: int, target_dim: int, min_scale: float):
    """``[N, 2 T D]`` head output -> ``loc``, ``scale`` ``[N, T, D]`` (softplus + floor)."""
    loc, raw_scale = raw.view(raw.shape[0], 2, horizon, target_dim).unbind(1)
    return loc, F.softplus(raw_scale) + min_scale


def student_batch(td: TensorDictBase, modalities: list[ModalitySpec]) -> TensorDictBase | None:
    """``L_mis``'s student input (:class:`~mmf_rl.objectives.MissingModalityLoss`): the observations and
    presence of ``td`` with the ``("drop", m)`` modalities made absent; ``None`` when ``td`` has no such
    masks. The baselines read presence per window only, so a step cut (``("drop_steps", m)``) is refused."""
    if any(keys.drop_steps_key(s.name) in td.keys(include_nested=True) for s in modalities):
        raise ValueError(
            "batch has ('drop_steps', m) masks (L_mis step cuts, loss.step_drop_prob > 0), which this "
            "baseline cannot apply: it reads presence per window, not per step; set loss.step_drop_prob=0 "
            "or use model=forecaster"
        )
    drop = keys.drop_masks(td, modalities)
    if drop is None:
        return None
    student = td.select(*[s.obs_key for s in modalities], *[s.present_key for s in modalities])
    for i, spec in enumerate(modalities):
        student.set(spec.present_key, td.get(spec.present_key) & ~drop[:, i])
    if not presence(student, modalities).any(1).all():
        raise ValueError(
            "('drop', m) removes every present modality of some sample; keep at least one per sample"
        )
    return student


def with_student(td: TensorDictBase, student: TensorDictBase) -> TensorDictBase:
    """The teacher's inputs (``td``'s keys that ``student`` has) followed by the student's, ``[2B]``: one
    pass computes both forecasts, as the paper model does."""
    return torch.cat([td.select(*student.keys(include_nested=True, leaves_only=True)), student], dim=0)


class DeterministicForecaster(TensorDictModuleBase, PretrainedModel):
    """Base of the baselines without a latent: ``forward`` computes ``loc``/``scale``; ``sample``
    repeats the mean ``K`` times (best-of-K of a deterministic model is its single forecast)."""

    def __init__(self, config: BaselineConfig):
        super().__init__()
        self.config = config
        self.modalities = list(config.modalities)
        self.scale_calibration = PresenceScaleCalibration(len(self.modalities), config.horizon)
        self.in_keys = [s.obs_key for s in self.modalities] + [s.present_key for s in self.modalities]
        self.out_keys = [keys.FORECAST_LOC, keys.FORECAST_SCALE]

    def validate(self, td: TensorDictBase) -> None:
        validate_baseline_batch(td, self.config)

    def forecast(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Writes ``("forecast", ...)``; with ``("drop", m)`` masks (``L_mis``) also
        ``("forecast_dropped", ...)``, the forecast without those modalities, in the same pass."""
        self.validate(td)
        student = student_batch(td, self.modalities)
        if student is None:
            loc, scale = self.forecast(td)
        else:
            loc, scale = self.forecast(with_student(td, student))
            (loc, dropped_loc), (scale, dropped_scale) = loc.chunk(2), scale.chunk(2)
            td.set(keys.FORECAST_DROPPED_LOC, dropped_loc)
            td.set(
                keys.FORECAST_DROPPED_SCALE,
                self.scale_calibration(dropped_scale, presence(student, self.modalities)),
            )
        td.set(keys.FORECAST_LOC, loc)
        td.set(keys.FORECAST_SCALE, self.scale_calibration(scale, presence(td, self.modalities)))
        return td

    def sample(self, td: TensorDictBase, num_samples: int = 20) -> TensorDictBase:
        """Write ``("forecast", "samples")`` ``[B, K, T, D]``: the point forecast ``K`` times.

        Args:
            td (TensorDictBase): a batch following `mmf_rl.keys`; written in place.
            num_samples (int, optional): ``K``. Defaults to ``20``.

        Returns:
            ``td``.
        """
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, found {num_samples}")
        self.validate(td)
        loc, _ = self.forecast(td)
        td.set(keys.FORECAST_SAMPLES, loc.unsqueeze(1).expand(-1, num_samples, -1, -1))
        return td
