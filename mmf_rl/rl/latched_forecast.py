"""A forecast that carries a policy through a sensor outage: `LatchedForecastTransform`.

When the camera dies, a `ForecastTransform` forecasts from the sensors left, which may not locate
the object at all. This transform also keeps, per env, the last forecast made while a chosen set
of sensors (by default every camera) was present for the whole window, and while they stay off
serves that forecast advanced by the time elapsed (alone, or combined with the fresh one by a rule:
by default their precision-weighted mean), with its age, so a policy knows how old it is::

    env = TransformedEnv(SerialEnv(4, make_env), Compose(
        ModalityDropout(["image"], outage="dies", seed=0),
        LatchedForecastTransform.from_checkpoint("runs/push/checkpoints"),
    ))
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from tensordict import NestedKey, TensorDictBase
from torch import nn
from torchrl.data import Composite, Unbounded

from mmf_rl import keys
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.envs.modality_dropout import reset_rows
from mmf_rl.rl.demonstrations import Demonstrations, ForecastTable
from mmf_rl.rl.transforms import ForecastTransform

# How a latched forecast and a fresh one (from the sensors left) are combined during an outage.
RULES = ("latched", "fresh", "scale", "precision")
# The per-env latch: its forecast and reference (target units), its age, whether there is one; and
# the reference's last readable value.
_LATCH_BUFFERS = (
    "_latched_loc",
    "_latched_scale",
    "_latched_reference",
    "_age",
    "_has_latch",
    "_last_reference",
)


class LatchedForecastTransform(ForecastTransform):
    """A `ForecastTransform` that, per env, latches the forecast made with ``latch_on`` present and
    serves it advanced through their outage; writes ``("forecast", "age")`` besides the forecast.

    Every step the fresh forecast is computed as `ForecastTransform` does. An env whose
    ``latch_on`` sensors are all present for the whole window latches it: the forecast is served
    as is, with age 0. With ``per_step_presence`` (a model trained on partial windows) present at
    the window's newest step is enough: a sensor that drops out in bursts seldom fills a window,
    and such a model forecasts from the steps it has. While one of them is absent, the latched
    forecast is advanced by the env steps elapsed since it was made, in whole forecast steps
    (``age // stride``): the step ``k`` served is the latched step ``shift + k``. Past the latched
    horizon the last latched step is held, its variance growing per forecast step as much as over
    the latched forecast's last step (it gets no surer); ``age >= T * stride`` says that the whole
    forecast served is that held step. The served forecast is re-based to the current step:

    * absolute target: as is;
    * ``relative`` target (a displacement from the current value): minus the latched forecast's
      own prediction of the current value, so it stays a displacement from now;
    * a target ``relative_to`` a reference (the object minus the gripper): plus the reference's
      motion since the latch, read from the env (``reference``: its key and dims; the gripper
      position is proprioception, present through a camera outage). While the reference is
      unreadable (its ``("present", m)`` flag off, or NaN/Inf) its last readable value stands in.

    The scale served is the latched scale at the same latched step. ``rule`` chooses, per env in
    an outage, between the advanced latch and the fresh forecast: ``"latched"``, ``"fresh"``,
    ``"scale"`` (the one whose mean predicted scale is smaller) or ``"precision"`` (their
    precision-weighted combination per step and dim, scale ``(1/s1² + 1/s2²)^-1/2``). The age
    written is the latch's where the latched forecast is served or combined, else 0. A reset
    clears the latch of the envs it resets. The latch is module state like the history (buffers:
    ``state_dict`` carries it, ``.to(device)`` moves it).

    Args:
        model (nn.Module): as `ForecastTransform`.
        stats (Mapping[str, torch.Tensor]): as `ForecastTransform`.

    Keyword Args:
        stride (int, optional): as `ForecastTransform`. Defaults to ``1``.
        latch_on (Sequence[str], optional): the modalities whose presence makes a forecast worth
            latching (default: every image modality).
        rule (str, optional): one of ``RULES``. The default, ``"precision"``, forecasts the object best
            through a camera outage on held-out push episodes, for a relative target and one relative
            to the gripper alike (`benchmarks/latched_forecast_outage.py`).
        relative (bool, optional): the model forecasts displacements from the target's current value
            (``data.target.relative``). Defaults to ``False``.
        reference (tuple[NestedKey, Sequence[int]], optional): ``(env key, dims)`` of the reference a
            ``data.target.relative_to`` target is measured from, read raw (in the target's units) from
            the env's output.
        denormalize (bool, optional): as `ForecastTransform`. Defaults to ``True``.
        trace (bool, optional): as `ForecastTransform`. Defaults to ``True``.
        per_step_presence (bool, optional): as `ForecastTransform` (applies to the fresh forecast).
            Defaults to ``False``.

    Raises:
        ValueError: an unknown ``rule``, both ``relative`` and ``reference``, a ``latch_on`` the model
            does not read, or a bad ``reference``; and what `ForecastTransform` raises.
    """

    def __init__(
        self,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        *,
        stride: int = 1,
        latch_on: Sequence[str] | None = None,
        rule: str = "precision",
        relative: bool = False,
        reference: tuple[NestedKey, Sequence[int]] | None = None,
        denormalize: bool = True,
        trace: bool = True,
        per_step_presence: bool = False,
    ):
        super().__init__(
            model,
            stats,
            stride=stride,
            denormalize=denormalize,
            trace=trace,
            per_step_presence=per_step_presence,
        )
        self.out_keys.append(keys.FORECAST_AGE)
        self._latch_modalities = self._latch_indices(latch_on)
        if rule not in RULES:
            raise ValueError(
                f"LatchedForecastTransform: unknown rule {rule!r}; expected one of {list(RULES)}"
            )
        if relative and reference is not None:
            raise ValueError(
                "LatchedForecastTransform: a target is relative to its own current value (relative=True) "
                "or to a reference, not both (data.target.relative / data.target.relative_to)"
            )
        self.rule, self.relative = rule, relative
        self._set_reference(reference)
        device, shape = self._slots.device, (0, self.horizon, self.target_dim)
        self.register_buffer("_latched_loc", torch.zeros(shape, device=device))
        self.register_buffer("_latched_scale", torch.ones(shape, device=device))
        self.register_buffer("_latched_reference", torch.zeros(0, self.target_dim, device=device))
        self.register_buffer("_last_reference", torch.zeros(0, self.target_dim, device=device))
        self.register_buffer("_age", torch.zeros(0, dtype=torch.long, device=device))
        self.register_buffer("_has_latch", torch.zeros(0, dtype=torch.bool, device=device))
        self._age_increment = 1  # 1 on a step, 0 on a reset (the envs not reset did not move)

    def _set_reference(self, reference: tuple[NestedKey, Sequence[int]] | None) -> None:
        self.reference_key = None if reference is None else reference[0]
        # The presence flag of an ("obs", m) reference: an absent sensor's values are no reading.
        self._reference_present_key = None
        key = self.reference_key
        if isinstance(key, tuple) and len(key) == 2 and key[0] == keys.OBS:
            self._reference_present_key = keys.present_key(key[1])
        if reference is None:
            return
        dims = torch.as_tensor(list(reference[1]), dtype=torch.long)
        if dims.numel() != self.target_dim:
            raise ValueError(
                f"LatchedForecastTransform: reference dims {dims.tolist()} give {dims.numel()} values, "
                f"the target has {self.target_dim}; give one reference dim per target dim"
            )
        self.register_buffer("_reference_dims", dims.to(self._slots.device), persistent=False)

    def _latch_indices(self, latch_on: Sequence[str] | None) -> list[int]:
        names = [s.name for s in self.specs]
        if latch_on is None:
            latch_on = [s.name for s in self.specs if s.kind == "image"]
        unknown = sorted(set(latch_on) - set(names))
        if unknown or not latch_on:
            raise ValueError(
                f"LatchedForecastTransform: latch_on must name some of the model's modalities {names}, "
                f"found {list(latch_on)}"
                + (" (the model has no image modality: name one)" if not latch_on else "")
            )
        return [names.index(name) for name in latch_on]

    @classmethod
    def for_trained(
        cls,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        data_config: Mapping,
        *,
        per_step_presence: bool | None = None,
        **options,
    ) -> LatchedForecastTransform:
        """The transform of a trained model (`load_trained_model`'s triple): the stride, the target
        frame (``relative`` / ``relative_to``, whose feature must be one of the model's modalities:
        the env emits it) and per-step presence (``partial_windows``; an explicit
        ``per_step_presence`` overrides it, `trained_per_step_presence`) from its data config."""
        relative, reference = target_frame(data_config, model.config.target_dim)
        return super().for_trained(
            model,
            stats,
            data_config,
            per_step_presence=per_step_presence,
            relative=relative,
            reference=reference,
            **options,
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        observation_spec = super().transform_observation_spec(observation_spec)
        batch = observation_spec.shape
        observation_spec[keys.FORECAST_AGE] = Unbounded(batch, dtype=torch.float32)
        return observation_spec

    # -- state ---------------------------------------------------------------------------------

    def _batch_size_changed(self) -> None:
        super()._batch_size_changed()
        n = 0 if self._batch_size is None else self._batch_size.numel()
        if self._age.shape[0] != n:  # a state load of the same batch keeps the loaded latch
            for name in _LATCH_BUFFERS:
                current = getattr(self, name)
                setattr(self, name, current.new_zeros(n, *current.shape[1:]))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # The latch is shaped by the env batch of the saved transform: take its shape first.
        for name in _LATCH_BUFFERS:
            saved = state_dict.get(prefix + name)
            if saved is not None and saved.shape != getattr(self, name).shape:
                setattr(self, name, getattr(self, name).new_empty(saved.shape))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        if self._batch_size == tensordict_reset.batch_size:
            rows = reset_rows(tensordict, self._batch_size, self._batch_size, type(self).__name__)
            rows = rows.to(self._age.device)
            self._has_latch.masked_fill_(rows, False)
            self._age.masked_fill_(rows, 0)
        self._age_increment = 0
        try:
            return super()._reset(tensordict, tensordict_reset)
        finally:
            self._age_increment = 1

    # -- forecast ------------------------------------------------------------------------------

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = super()._emit(tensordict)
        batch, n = self._batch_size, self._batch_size.numel()
        loc = tensordict.get(keys.FORECAST_LOC).reshape(n, self.horizon, self.target_dim)
        scale = tensordict.get(keys.FORECAST_SCALE).reshape(n, self.horizon, self.target_dim)
        normalizer = self.normalizer
        if not self.denormalize:  # the latch is kept in the target's units (where re-basing is a sum)
            loc, scale = normalizer.denormalize_target(loc), normalizer.denormalize_target_scale(scale)
        reference = self._reference(tensordict, n)
        fresh = self._latch(loc, scale, reference)
        held_loc, held_scale = self.advanced(reference)
        outage = ~fresh & self._has_latch
        loc, scale, age, latched = choose(self.rule, outage, self._age, loc, scale, held_loc, held_scale)
        if not self.denormalize:
            loc = normalizer.normalize("target", loc)
            scale = scale / normalizer.stats["target/std"]
        tensordict.set(keys.FORECAST_LOC, loc.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_SCALE, scale.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_VALID, tensordict.get(keys.FORECAST_VALID) | latched.reshape(batch))
        tensordict.set(keys.FORECAST_AGE, age.reshape(batch))
        return tensordict

    def _reference(self, tensordict: TensorDictBase, n: int) -> torch.Tensor | None:
        """The reference's current value ``[n, D]`` (target units; its last readable value where it
        cannot be read now), when the target has one."""
        if self.reference_key is None:
            return None
        values = tensordict.get(self.reference_key).reshape(n, -1).to(self._age.device)
        values = values.index_select(1, self._reference_dims).float()
        readable = torch.isfinite(values).all(1)
        if self._reference_present_key is not None:
            readable &= tensordict.get(self._reference_present_key).reshape(n).to(readable.device)
        self._last_reference.copy_(torch.where(readable[:, None], values, self._last_reference))
        return self._last_reference

    def _latch(self, loc: torch.Tensor, scale: torch.Tensor, reference: torch.Tensor | None) -> torch.Tensor:
        """Latch the fresh forecast of the envs whose ``latch_on`` sensors fill the window (with
        ``per_step_presence``: hold its newest step); age the others. Returns those envs ``[n]``."""
        slots = self._slots[self._newest]
        fresh = torch.ones_like(self._has_latch)
        for i in self._latch_modalities:
            # A vector modality's window is its last step; a model trained on partial windows
            # forecasts from any window whose newest step holds the sensor.
            if self.specs[i].kind == "vector" or self.per_step_presence:
                fresh &= self._presence(i)[:, self._newest]
            else:
                fresh &= self._presence(i).index_select(1, slots).all(1)
        keep = fresh.view(-1, 1, 1)
        self._latched_loc.copy_(torch.where(keep, loc, self._latched_loc))
        self._latched_scale.copy_(torch.where(keep, scale, self._latched_scale))
        if reference is not None:
            self._latched_reference.copy_(torch.where(fresh.view(-1, 1), reference, self._latched_reference))
        self._age.copy_(torch.where(fresh, 0, self._age + self._age_increment))
        self._has_latch |= fresh
        return fresh

    def advanced(self, reference: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Every env's latched forecast advanced by its age and re-based to the current step:
        ``loc``, ``scale`` ``[n, T, D]`` in the target's units (see the class doc). ``reference``:
        its current value ``[n, D]`` for a ``relative_to`` target."""
        motion = None if reference is None else reference - self._latched_reference
        return advance(self._latched_loc, self._latched_scale, self._age, self.stride, self.relative, motion)


def advance(
    loc: torch.Tensor,
    scale: torch.Tensor,
    age: torch.Tensor,
    stride: int,
    relative: bool,
    reference_motion: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forecasts ``loc``, ``scale`` ``[n, T, D]`` (target units) made ``age`` ``[n]`` env steps ago,
    served for now (`LatchedForecastTransform`'s rules): shifted by ``age // stride`` forecast steps,
    the last step held past the horizon (its variance growing); a ``relative`` target minus the
    forecast's own prediction of the current value; a target relative to a reference minus the
    reference's motion since (``reference_motion`` ``[n, D]``: now minus then)."""
    horizon, dim = loc.shape[1:]
    forecast_steps = torch.div(age, stride, rounding_mode="floor")
    latched_step = forecast_steps[:, None] + torch.arange(1, horizon + 1, device=loc.device)  # [n, T]
    shift = forecast_steps.clamp(max=horizon)
    index = (latched_step.clamp(max=horizon) - 1)[:, :, None].expand(-1, -1, dim)
    held_loc, held_scale = loc.gather(1, index), scale.gather(1, index)
    # Past the horizon the held step grows no surer: its variance keeps growing at the rate of the
    # forecast's own last step.
    before_last = scale[:, -2] if horizon > 1 else torch.zeros_like(scale[:, -1])
    growth = (scale[:, -1].square() - before_last.square()).clamp(min=0)  # [n, D] per forecast step
    excess = (latched_step - horizon).clamp(min=0)[:, :, None]
    held_scale = (held_scale.square() + excess * growth[:, None, :]).sqrt()
    if relative:
        # The forecast's own prediction of the current value (0 when it is fresh).
        now = loc.gather(1, (shift - 1).clamp(min=0).view(-1, 1, 1).expand(-1, 1, dim))
        held_loc = held_loc - now * (shift > 0).view(-1, 1, 1)
    elif reference_motion is not None:
        held_loc = held_loc - reference_motion[:, None, :]
    return held_loc, held_scale


def choose(
    rule: str,
    outage: torch.Tensor,
    age: torch.Tensor,
    loc: torch.Tensor,
    scale: torch.Tensor,
    held_loc: torch.Tensor,
    held_scale: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per row where ``outage`` ``[n]``, the fresh forecast (``loc``, ``scale``), the advanced latch
    (``held_*``) or their combination by ``rule`` (`RULES`); elsewhere the fresh one. Returns
    ``loc``, ``scale``, the age served (float ``[n]``: ``age`` where the latch is used, else 0) and
    where it is used ``[n]``."""
    if rule == "fresh":
        use = torch.zeros_like(outage)
    elif rule == "scale":
        use = outage & (held_scale.mean((1, 2)) < scale.mean((1, 2)))
    else:
        use = outage
    served_age = torch.where(use, age, 0).float()
    keep = use.view(-1, 1, 1)
    if rule == "precision":
        fresh_precision, held_precision = scale.pow(-2), held_scale.pow(-2)
        total = fresh_precision + held_precision
        combined_loc = (loc * fresh_precision + held_loc * held_precision) / total
        return combined_loc.where(keep, loc), total.rsqrt().where(keep, scale), served_age, use
    return held_loc.where(keep, loc), held_scale.where(keep, scale), served_age, use


@dataclass
class LatchedForecastTable:
    """What `LatchedForecastTransform` serves a policy at each demonstration frame, for training
    it offline: a `ForecastTable`'s forecasts, latched and advanced as the transform does.

    A sample whose ``latch_on`` sensors are out (the loader's outage) is given an age ``a``: its
    camera died ``a`` env steps before, so the latch is the forecast of frame ``f - a`` with those
    sensors present (and the sample's other outages), advanced and re-based by `advance`, then
    chosen or combined with the sample's fresh forecast by ``rule`` (`choose`). The age is drawn
    per sample: with probability ``never_latched`` none (the sensor was never seen in the episode:
    the fresh forecast, age 0), else uniform in ``1 .. min(max_age, f - episode start)``. The
    frames before an outage are assumed to have had the sensors (true of the recorded pushes).
    Batches carry ``("forecast", "loc"/"scale")`` in the forecaster's normalised frame and
    ``("forecast", "age")``.

    Args:
        table (ForecastTable): the forecaster's table; ``latch_on`` must be among its ``droppable``.
        demonstrations (Demonstrations): its demonstrations (episode starts, the reference's raw
            values).
        stats (Mapping[str, torch.Tensor]): the forecaster's normalisation statistics (the latch is
            re-based in target units).
        rule (str, optional): as `LatchedForecastTransform`. Defaults to ``"precision"``.
        stride (int, optional): the forecaster's data stride. Defaults to ``1``.
        relative (bool, optional): as `LatchedForecastTransform` (`target_frame` reads it from a run's
            data config). Defaults to ``False``.
        reference (tuple[NestedKey, Sequence[int]], optional): as `LatchedForecastTransform`, an
            ``("obs", m)`` key of the demonstrations.
        latch_on (tuple[str, ...], optional): as `LatchedForecastTransform`. Defaults to
            ``("image",)``.
        max_age (int, optional): the largest age drawn, in env steps. Defaults to ``50``.
        never_latched (float, optional): the probability of no latch (the fresh forecast, age 0).
            Defaults to ``0.2``.

    Raises:
        ValueError: an unknown ``rule``, a ``latch_on`` the table does not cover, ``max_age < 1``,
            ``never_latched`` outside ``[0, 1]`` or a reference that is not an ``("obs", m)`` key.
    """

    table: ForecastTable
    demonstrations: Demonstrations
    stats: Mapping[str, torch.Tensor]
    rule: str = "precision"
    stride: int = 1
    relative: bool = False
    reference: tuple[NestedKey, Sequence[int]] | None = None
    latch_on: tuple[str, ...] = ("image",)
    max_age: int = 50
    never_latched: float = 0.2

    def __post_init__(self):
        if self.rule not in RULES:
            raise ValueError(
                f"LatchedForecastTable: unknown rule {self.rule!r}; expected one of {list(RULES)}"
            )
        if not self.latch_on or set(self.latch_on) - set(self.table.droppable):
            raise ValueError(
                f"LatchedForecastTable: latch_on {list(self.latch_on)} must be outages the ForecastTable "
                f"covers ({list(self.table.droppable)}); compute it with droppable including them"
            )
        self.latch_on = tuple(self.latch_on)
        if self.max_age < 1 or not 0.0 <= self.never_latched <= 1.0:
            raise ValueError(
                f"LatchedForecastTable: max_age must be >= 1 and never_latched in [0, 1], found "
                f"{self.max_age}, {self.never_latched}"
            )
        key = self.reference[0] if self.reference is not None else None
        if key is not None and not (isinstance(key, tuple) and len(key) == 2 and key[0] == keys.OBS):
            raise ValueError(
                f"LatchedForecastTable: the reference must be a modality the demonstrations hold, an "
                f"('obs', m) key, found {key!r}"
            )
        self.normalizer = Normalizer(dict(self.stats))

    @classmethod
    def for_trained(
        cls,
        table: ForecastTable,
        demonstrations: Demonstrations,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        data_config: Mapping,
        **options,
    ) -> LatchedForecastTable:
        """The table of ``table``'s trained forecaster (`load_trained_model`'s triple), with the stride
        and target frame of its data config, as `LatchedForecastTransform.for_trained` reads them;
        ``options``: ``rule``, ``latch_on``, ``max_age``, ``never_latched``."""
        relative, reference = target_frame(data_config, model.config.target_dim)
        stride = int(data_config.get("stride", 1))
        return cls(
            table, demonstrations, stats, stride=stride, relative=relative, reference=reference, **options
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.table.shape

    @property
    def droppable(self) -> tuple[str, ...]:
        return self.table.droppable

    def served(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor], ages: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``loc``, ``scale`` (normalised) and age (float) served at ``frames`` whose latch is
        ``ages`` ``[B]`` env steps old (0: none, the fresh forecast)."""
        loc, scale = self.table.lookup(frames, absent)
        source = frames - ages
        with_sensors = {m: a for m, a in absent.items() if m not in self.latch_on}
        latched_loc, latched_scale = self.table.lookup(source, with_sensors)
        units = self.normalizer
        motion = None
        if self.reference is not None:
            name, dims = self.reference[0][1], list(self.reference[1])
            observed = self.demonstrations.observation
            motion = observed(name, frames)[:, dims] - observed(name, source)[:, dims]
        held = advance(
            units.denormalize_target(latched_loc),
            units.denormalize_target_scale(latched_scale),
            ages,
            self.stride,
            self.relative,
            motion,
        )
        fresh = units.denormalize_target(loc), units.denormalize_target_scale(scale)
        loc, scale, age, _ = choose(self.rule, ages > 0, ages, *fresh, *held)
        return units.normalize("target", loc), scale / units.stats["target/std"], age

    def draw_ages(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor], generator: torch.Generator
    ) -> torch.Tensor:
        """The latch ages of ``frames`` (see the class doc): 0 unless a ``latch_on`` sensor is out."""
        n = len(frames)
        none = torch.zeros(n, dtype=torch.bool)
        out = torch.stack([absent.get(m, none) for m in self.latch_on]).any(0)
        # Drawn for every sample: the stream does not depend on outcomes.
        never, uniform = torch.rand(n, generator=generator), torch.rand(n, generator=generator)
        longest = (frames - self.demonstrations.episode_start(frames)).clamp(max=self.max_age)
        ages = (uniform * longest).long() + 1
        return torch.where(out & (never >= self.never_latched) & (longest > 0), ages, 0)

    def entries(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor], generator: torch.Generator
    ) -> dict[tuple[str, str], torch.Tensor]:
        """``("forecast", "loc"/"scale"/"age")`` of ``frames`` (`DemonstrationLoader`)."""
        loc, scale, age = self.served(frames, absent, self.draw_ages(frames, absent, generator))
        return {keys.FORECAST_LOC: loc, keys.FORECAST_SCALE: scale, keys.FORECAST_AGE: age}


def target_frame(data_config: Mapping, target_dim: int) -> tuple[bool, tuple[NestedKey, list[int]] | None]:
    """``relative`` and ``reference`` (env key, dims) of a run's target, from its data config."""
    target = data_config.get("target", {})
    reference = _reference_in_env(target.get("relative_to"), data_config.get("modalities", {}), target_dim)
    return bool(target.get("relative", False)), reference


def _reference_in_env(
    relative_to: Mapping | None, modalities: Mapping, target_dim: int
) -> tuple[NestedKey, list[int]] | None:
    """``data.target.relative_to`` as the env key and dims it is read from: the ``("obs", m)`` of the
    modality that reads the same feature (its dims mapped through the modality's ``dims``)."""
    if not relative_to:
        return None
    feature = relative_to["feature"]
    dims = relative_to.get("dims") or list(range(target_dim))  # unset: the whole feature
    for name, modality in modalities.items():
        modality = {"feature": modality} if isinstance(modality, str) else modality
        kept = modality.get("dims") or list(range(max(dims) + 1))
        if modality["feature"] == feature and set(dims) <= set(kept):
            return keys.obs_key(name), [kept.index(d) for d in dims]
    raise ValueError(
        f"LatchedForecastTransform: the target is relative to {feature!r} dims {dims}, which no model "
        f"modality reads ({dict(modalities)}), so the env does not emit it; pass reference=(env key, dims)"
    )
