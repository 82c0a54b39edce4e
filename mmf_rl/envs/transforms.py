"""TorchRL transforms for multimodal envs: simulated sensor outages and a live forecaster.

Both read the `mmf_rl.keys` contract per env step (``("obs", m)`` single frames and
``("present", m)`` flags, as `MultimodalPushTorchEnv` emits them) and keep per-env state shaped
by the env's batch size, so they work on a single env and on `SerialEnv`/`ParallelEnv` alike.

* `ModalityDropout`: seeded outages per modality (bursts of steps, or whole episodes); an absent
  modality's data is zeroed and its ``("present", m)`` flag cleared. Specs are unchanged.
* `ForecastTransform`: rolling history of the last H steps, a trained forecaster run on it every
  step (one batched forward over all envs), the forecast written to ``("forecast", ...)``.
* `HistoryWindow`: the same rolling history, written as a model batch under ``"history"`` for a
  policy that runs its own model on it (a planner with a world model).

Put the dropout before the forecaster::

    env = TransformedEnv(SerialEnv(4, make_env), Compose(
        ModalityDropout(["image", "force"], outage_prob=0.05, bursts=UniformBursts(3, 10), seed=0),
        ForecastTransform.from_checkpoint("runs/push/checkpoints"),
    ))
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import Compose, Transform

from mmf_rl import keys
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.keys import ModalitySpec

RESET_KEY = "_reset"


def _reset_rows(tensordict: TensorDictBase, batch_size: torch.Size, known_batch_size: torch.Size | None,
                owner: str) -> torch.Tensor:
    """The envs a reset applies to, flattened to ``[n]``: ``"_reset"`` if given, else all.

    A transform allocates its per-env state on the first reset of a batch shape, so a batch it
    has not seen must be reset whole.
    """
    n = batch_size.numel()
    reset = tensordict.get(RESET_KEY, None) if tensordict is not None else None
    # "_reset" carries the done spec's trailing dim ([*batch, 1]).
    rows = torch.ones(n, dtype=torch.bool) if reset is None else reset.reshape(n, -1).any(-1).cpu()
    if known_batch_size != batch_size and not rows.all():
        raise RuntimeError(f"{owner}: partial reset of an env batch {list(batch_size)} it has not seen; "
                           "reset every env first")
    return rows


def _not_standalone(name: str) -> RuntimeError:
    return RuntimeError(f"{name} keeps per-env state across steps and only runs inside a TransformedEnv "
                        "(env.reset / env.step); it cannot be applied to a stored tensordict")


# -- ModalityDropout ---------------------------------------------------------------------------


@dataclass(frozen=True)
class UniformBursts:
    """Outage lengths uniform over ``[min_steps, max_steps]`` steps (inclusive)."""

    min_steps: int
    max_steps: int

    def __post_init__(self):
        if not 1 <= self.min_steps <= self.max_steps:
            raise ValueError(f"UniformBursts needs 1 <= min_steps <= max_steps, found "
                             f"min_steps={self.min_steps}, max_steps={self.max_steps}")

    def sample(self, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
        return torch.randint(self.min_steps, self.max_steps + 1, shape, generator=generator)


@dataclass(frozen=True)
class GeometricBursts:
    """Outage lengths geometric on ``{1, 2, ...}`` with mean ``mean_steps`` (memoryless recovery)."""

    mean_steps: float

    def __post_init__(self):
        if not self.mean_steps >= 1:
            raise ValueError(f"GeometricBursts needs mean_steps >= 1, found {self.mean_steps}")

    def sample(self, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
        if self.mean_steps == 1:
            return torch.ones(shape, dtype=torch.long)
        # Inverse CDF: P(L > k) = (1 - p)^k with p = 1 / mean.
        u = 1.0 - torch.rand(shape, generator=generator, dtype=torch.float64)  # (0, 1]
        return (torch.log(u) / math.log(1.0 - 1.0 / self.mean_steps)).floor().long() + 1


def outage_start_prob(fraction: float, mean_burst: float) -> float:
    """The per-step outage start probability (``ModalityDropout(per="step")``'s ``outage_prob``) that
    leaves a modality absent ``fraction`` of the steps when its outages last ``mean_burst`` steps on
    average.

    Up runs last ``1 / p`` steps on average (an outage starts with probability ``p`` at each step
    the modality is up), outages ``mean_burst``, so the absent fraction is
    ``mean_burst / (mean_burst + 1 / p)``. A fraction above ``mean_burst / (mean_burst + 1)`` would
    need ``p > 1``: it is capped there (an outage after every single reading).
    """
    if not 0.0 <= fraction < 1.0 or mean_burst < 1:
        raise ValueError(f"outage_start_prob needs 0 <= fraction < 1 and mean_burst >= 1, found fraction={fraction}, "
                         f"mean_burst={mean_burst}")
    return min(1.0, fraction / (mean_burst * (1.0 - fraction)))


def replay_outages(outages: Mapping[str, Mapping[str, float]], seed: int = 0) -> Compose:
    """One ``ModalityDropout`` per modality that replays measured outages: ``{modality: {"fraction":
    f, "mean_burst": L}}`` (what ``mmf-rl inspect`` reports and ``WindowDataset.observed_outages``
    holds) becomes outages that start with ``outage_start_prob(f, L)`` and last ``GeometricBursts(L)``.
    Modalities never or always absent (``f`` of 0 or 1) get no transform."""
    transforms = [
        ModalityDropout([name], outage_prob=outage_start_prob(o["fraction"], o["mean_burst"]),
                        bursts=GeometricBursts(o["mean_burst"]), per="step", seed=seed + i)
        for i, (name, o) in enumerate(sorted(outages.items())) if 0.0 < o["fraction"] < 1.0
    ]
    if not transforms:
        raise ValueError(f"replay_outages: no modality in {sorted(outages)} has outages to replay (every fraction is "
                         "0 or 1)")
    return Compose(*transforms)


class ModalityDropout(Transform):
    """Seeded sensor outages: zero ``("obs", m)`` and clear ``("present", m)`` while ``m`` is out.

    Args:
        modalities: names of the modalities that can fail.
        outage_prob: one probability for all, or one per modality (a mapping over ``modalities``).
            ``per="step"``: probability that an outage starts at a step where the modality is up;
            ``per="episode"``: probability that the modality is out for the whole episode.
        bursts: outage length distribution for ``per="step"`` (`UniformBursts` or
            `GeometricBursts`); an outage lasts exactly the drawn number of steps unless the
            episode ends first.
        per: ``"step"`` (bursts) or ``"episode"``.
        seed: seed of the transform's own ``torch.Generator``; the same seed, env batch size and
            sequence of resets and steps give the same outages.

    Every env (every row of a batched env) draws independently. The reset observation counts as
    a step. After an outage the modality delivers at least one reading before it can fail again,
    so each outage is one run of absent steps of the drawn length. A reset clears the outages of
    the envs that reset (honouring ``"_reset"`` masks) and draws afresh for them.
    """

    def __init__(self, modalities: Sequence[str], outage_prob: float | Mapping[str, float] = 0.05,
                 bursts: UniformBursts | GeometricBursts = UniformBursts(1, 10),
                 per: Literal["step", "episode"] = "step", seed: int = 0):
        modalities = list(modalities)
        if not modalities:
            raise ValueError("ModalityDropout needs at least one modality name")
        if per not in ("step", "episode"):
            raise ValueError(f"ModalityDropout(per={per!r}): expected 'step' or 'episode'")
        if isinstance(outage_prob, Mapping):
            unknown = sorted(set(outage_prob) - set(modalities))
            missing = sorted(set(modalities) - set(outage_prob))
            if unknown or missing:
                raise ValueError(f"ModalityDropout: outage_prob names {sorted(outage_prob)} but modalities are "
                                 f"{modalities}; give one probability per modality")
            probs = [float(outage_prob[m]) for m in modalities]
        else:
            probs = [float(outage_prob)] * len(modalities)
        if any(not 0.0 <= p <= 1.0 for p in probs):
            raise ValueError(f"ModalityDropout: outage probabilities must be in [0, 1], found {probs}")
        obs_keys = [keys.obs_key(m) for m in modalities]
        present_keys = [keys.present_key(m) for m in modalities]
        super().__init__(in_keys=obs_keys + present_keys, out_keys=obs_keys + present_keys)
        self.modalities = modalities
        self.outage_prob = torch.tensor(probs)
        self.bursts = bursts
        self.per = per
        self.seed = seed
        self.generator = torch.Generator().manual_seed(seed)
        # Per env (flattened batch) and modality: steps of the current outage still to come, and
        # whether the last observation was absent.
        self._remaining: torch.Tensor | None = None
        self._absent: torch.Tensor | None = None
        self._batch_size: torch.Size | None = None

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        available = sorted(k[1] for k in observation_spec.keys(True, True) if isinstance(k, tuple) and k[0] == keys.OBS)
        missing = [k for k in self.in_keys if k not in observation_spec.keys(True, True)]
        if missing:
            raise KeyError(f"ModalityDropout: the env has no {missing}; its modalities are {available}")
        return observation_spec

    def _draw(self, rows: torch.Tensor) -> None:
        """Advance the outage state of ``rows`` by one observation."""
        shape = self._remaining.shape
        # Draws for every row and modality each time, so the stream does not depend on outcomes.
        starts = torch.rand(shape, generator=self.generator) < self.outage_prob
        if self.per == "step":
            lengths = self.bursts.sample(shape, self.generator)
        else:  # drawn at reset only: an outage that outlasts any episode
            lengths = torch.full(shape, torch.iinfo(torch.long).max)
        starts &= ~self._absent & rows[:, None]
        remaining = torch.where(starts, lengths, self._remaining)
        absent = remaining > 0
        self._absent = torch.where(rows[:, None], absent, self._absent)
        self._remaining = torch.where(rows[:, None], (remaining - 1).clamp_min(0), self._remaining)

    def _apply_outages(self, tensordict: TensorDictBase) -> TensorDictBase:
        absent = self._absent.reshape(*self._batch_size, len(self.modalities))
        for i, name in enumerate(self.modalities):
            out = absent[..., i]
            obs = tensordict.get(keys.obs_key(name))
            mask = out.reshape(*out.shape, *[1] * (obs.dim() - out.dim()))
            tensordict.set(keys.obs_key(name), obs.masked_fill(mask, 0))
            tensordict.set(keys.present_key(name), tensordict.get(keys.present_key(name)) & ~out)
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        rows = _reset_rows(tensordict, batch_size, self._batch_size, "ModalityDropout")
        if self._batch_size != batch_size:
            self._batch_size = batch_size
            self._remaining = torch.zeros(batch_size.numel(), len(self.modalities), dtype=torch.long)
            self._absent = torch.zeros(batch_size.numel(), len(self.modalities), dtype=torch.bool)
        self._remaining[rows] = 0
        self._absent[rows] = False
        self._draw(rows)
        return self._apply_outages(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._batch_size is None:
            raise RuntimeError("ModalityDropout: the env was stepped before its first reset; call env.reset()")
        if self.per == "step":
            self._draw(torch.ones(self._batch_size.numel(), dtype=torch.bool))
        return self._apply_outages(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise _not_standalone("ModalityDropout")


# -- ForecastTransform -------------------------------------------------------------------------


def _describe_spec(spec, batch_dims: int) -> str:
    """dtype and per-env shape of a leaf spec."""
    return f"{str(spec.dtype).removeprefix('torch.')} {list(spec.shape[batch_dims:])}"


class _WindowTransform(Transform):
    """Keeps each env's last ``(H - 1) * stride + 1`` frames of every modality in a ring buffer and
    builds the model's input window from them, as the data pipeline does (see `ForecastTransform`
    for the rules). Subclasses say what to write each step (:meth:`_emit`) and add its specs.
    """

    def __init__(self, specs: Sequence[ModalitySpec], stats: Mapping[str, torch.Tensor], history: int,
                 stride: int, out_keys: list):
        self.specs: list[ModalitySpec] = list(specs)
        if stride < 1:
            raise ValueError(f"{type(self).__name__}: stride must be >= 1, found {stride}")
        required = [f"{s.name}/{stat}" for s in self.specs if s.kind != "image" for stat in ("mean", "std")]
        missing = [k for k in required + ["target/mean", "target/std"] if k not in stats]
        if missing:
            raise KeyError(f"{type(self).__name__}: normalisation stats lack {missing} (found {sorted(stats)}); "
                           "pass the stats of the run that trained the model (checkpoint.tensors)")
        in_keys = [s.obs_key for s in self.specs] + [s.present_key for s in self.specs]
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.normalizer = Normalizer(dict(stats))
        self.history, self.stride = history, stride
        self.buffer_length = (history - 1) * stride + 1
        self._frames: dict[str, torch.Tensor] = {}
        self._present: dict[str, torch.Tensor] = {}
        self._newest = 0  # ring slot of the newest frame, shared by all envs (a reset fills every slot)
        self._batch_size: torch.Size | None = None

    # -- specs ---------------------------------------------------------------------------------

    def _check_modalities(self, observation_spec: Composite) -> None:
        """The env must emit every model modality with a compatible kind and shape."""
        env_side = {k[1]: observation_spec[k] for k in observation_spec.keys(True, True)
                    if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.OBS}
        batch_dims = len(observation_spec.shape)
        problems = []
        for spec in self.specs:
            found = env_side.get(spec.name)
            if found is None:
                problems.append(f"{spec.name!r} is not emitted")
            elif spec.present_key not in observation_spec.keys(True, True):
                problems.append(f"{spec.name!r} has no {spec.present_key} flag")
            elif spec.kind == "image":
                if found.dtype != torch.uint8 or len(found.shape) < 3 or found.shape[-3] != spec.shape[0]:
                    problems.append(f"{spec.name!r} is {_describe_spec(found, batch_dims)}, expected uint8 "
                                    f"[{spec.shape[0]}, h, w]")
            elif not found.dtype.is_floating_point or tuple(found.shape[-1:]) != spec.shape:
                problems.append(f"{spec.name!r} is {_describe_spec(found, batch_dims)}, expected float {list(spec.shape)}")
        if problems:
            model_side = ", ".join(f"{s.name} ({s.kind} {list(s.shape)})" for s in self.specs)
            env_listing = ", ".join(f"{name} ({_describe_spec(s, batch_dims)})" for name, s in sorted(env_side.items()))
            raise ValueError(
                f"{type(self).__name__}: the checkpoint's modalities do not match the env's observations "
                f"({'; '.join(problems)}). Checkpoint modalities: [{model_side}]; env ('obs', m) keys: "
                f"[{env_listing}]. Use a checkpoint trained on this env's sensors (same names and sizes), "
                f"or configure the env to emit the modalities the model was trained on."
            )

    # -- history -------------------------------------------------------------------------------

    def _frame(self, spec: ModalitySpec, tensordict: TensorDictBase, n: int) -> torch.Tensor:
        """One step of ``spec`` for all envs, as the model's window stores it: ``[n, *shape]``."""
        try:
            value = tensordict.get(spec.obs_key)
        except KeyError:
            raise KeyError(f"{type(self).__name__}: the env output has no {spec.obs_key}; the model reads "
                           f"{[s.obs_key for s in self.specs]}") from None
        if spec.kind == "image":
            value = value.reshape(n, *value.shape[-3:])
            if tuple(value.shape[-2:]) != spec.shape[-2:]:
                # As the window cache resizes decoded frames (mmf_rl.datasets.lerobot_source).
                value = F.interpolate(value.float() / 255, size=spec.shape[-2:], mode="bilinear", antialias=True,
                                      align_corners=False)
                value = (value * 255).round_().clamp_(0, 255).to(torch.uint8)
            return value
        return self.normalizer.normalize(spec.name, value.reshape(n, *spec.shape).float())

    def _push(self, tensordict: TensorDictBase, rows: torch.Tensor | None) -> None:
        """Append this step's frame: to every env (``rows=None``), or fill the history of ``rows``."""
        n = self._batch_size.numel()
        if rows is None:
            self._newest = (self._newest + 1) % self.buffer_length
        for spec in self.specs:
            frame = self._frame(spec, tensordict, n)
            present = tensordict.get(spec.present_key).reshape(n)
            if rows is None:
                self._frames[spec.name][:, self._newest] = frame
                self._present[spec.name][:, self._newest] = present
            else:
                self._frames[spec.name][rows] = frame[rows].unsqueeze(1)
                self._present[spec.name][rows] = present[rows].unsqueeze(1)

    def _allocate(self, batch_size: torch.Size) -> None:
        n, length = batch_size.numel(), self.buffer_length
        self._batch_size = batch_size
        self._newest = 0
        for spec in self.specs:
            self._frames[spec.name] = torch.zeros(n, length, *spec.shape, dtype=spec.dtype)
            self._present[spec.name] = torch.zeros(n, length, dtype=torch.bool)

    def window(self) -> TensorDict:
        """The model's input for every env, ``[n]`` (flattened env batch), as the data pipeline builds it."""
        n = self._batch_size.numel()
        # Ring slots of the H window steps, oldest first.
        steps = torch.arange(self.history - 1, -1, -1) * self.stride
        slots = (self._newest - steps) % self.buffer_length
        window = TensorDict(batch_size=[n])
        for spec in self.specs:
            if spec.kind == "vector":
                values = self._frames[spec.name][:, self._newest]
                present = self._present[spec.name][:, self._newest]
            else:
                values = self._frames[spec.name].index_select(1, slots)
                present = self._present[spec.name].index_select(1, slots).all(1)
            if spec.kind != "image":
                values = values * present.view(-1, *[1] * (values.dim() - 1))
            window.set(spec.obs_key, values)
            window.set(spec.present_key, present)
        return window

    # -- env hooks -----------------------------------------------------------------------------

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        rows = _reset_rows(tensordict, batch_size, self._batch_size, type(self).__name__)
        if self._batch_size != batch_size:
            self._allocate(batch_size)
        self._push(tensordict_reset, rows)
        return self._emit(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._batch_size is None:
            raise RuntimeError(f"{type(self).__name__}: the env was stepped before its first reset; call env.reset()")
        self._push(next_tensordict, None)
        return self._emit(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise _not_standalone(type(self).__name__)


class ForecastTransform(_WindowTransform):
    """Runs a trained forecaster on the last H steps of every env; writes ``("forecast", ...)``.

    Args:
        model: a forecaster from the model registry (``config.modalities``, ``config.history``,
            ``config.horizon``, ``config.target_dim``); it is put in eval mode and run under
            ``torch.no_grad()``. An action-conditioned world model cannot forecast without the
            future actions: plan with it instead (`HistoryWindow` + `mmf_rl.planning`).
        stats: the normalisation statistics of its training run (a checkpoint's ``tensors``):
            ``"<m>/mean"``, ``"<m>/std"`` for every non-image modality, ``"target/mean"``,
            ``"target/std"``.
        stride: frames between two window steps (the data config's ``stride``).
        num_samples: ``K > 0`` also writes ``("forecast", "samples")`` ``[*batch, K, T, D]``, one
            forecast per prior latent draw (costs a second forward).
        denormalize: ``True`` writes forecasts in the target's units (for the push data: metres,
            world frame; a run trained with ``data.target.relative`` forecasts displacements from
            the current step, as the push config does), ``False`` in the normalised frame the
            model was trained in.

    Written every step (env batch ``[*batch]``): ``("forecast", "loc")`` and ``("forecast",
    "scale")`` ``float32 [*batch, T, D]`` (the model's deterministic eval forecast, a diagonal
    Gaussian), ``("forecast", "samples")`` when ``num_samples > 0``, and ``("forecast",
    "valid")`` ``bool [*batch]``.

    The window follows the data pipeline (`mmf_rl.datasets.windows`): vector observations are
    normalised with ``stats``; images are resized to the model's size the way the cache resizes
    them (bilinear, antialiased); a ``"sequence"``/``"image"`` modality is present in the window
    only if it is present at all H steps (``"vector"``: at the last step), and an absent
    modality's vector window is zeroed. After a reset, the first observation fills the whole
    history (its presence too), so a full window exists from the first step; it is replaced step
    by step over the next H-1 steps. A window with no present modality cannot be forecast: its
    row gets ``valid = False`` and the training marginal of the target (normalised mean 0,
    scale 1, i.e. ``target/mean`` and ``target/std`` in target units).

    The history is a fixed ring buffer per env: the cost per step does not grow with time.
    """

    def __init__(self, model: nn.Module, stats: Mapping[str, torch.Tensor], *, stride: int = 1,
                 num_samples: int = 0, denormalize: bool = True):
        config = model.config
        if getattr(config, "action_dim", 0):
            raise ValueError(
                "ForecastTransform: this model is an action-conditioned world model (action_dim="
                f"{config.action_dim}); it forecasts only under given future actions. Plan with it: "
                "HistoryWindow + mmf_rl.planning.SequenceCEMPlanner, or ForecasterWorldModelEnv"
            )
        if num_samples < 0:
            raise ValueError(f"ForecastTransform: num_samples must be >= 0, found {num_samples}")
        if num_samples and not hasattr(model, "sample"):
            raise ValueError(f"ForecastTransform: {type(model).__name__} has no latent to sample; use num_samples=0")
        out_keys = [keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.FORECAST_VALID]
        if num_samples:
            out_keys.append(keys.FORECAST_SAMPLES)
        super().__init__(config.modalities, stats, config.history, stride, out_keys)
        self.model = model.eval()
        self.horizon, self.target_dim = config.horizon, config.target_dim
        self.num_samples, self.denormalize = num_samples, denormalize

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike, *, num_samples: int = 0, denormalize: bool = True,
                        map_location: str | torch.device = "cpu") -> ForecastTransform:
        """Load the model, its weights, normalisation stats and window stride from a checkpoint.

        ``path``: a checkpoint directory or a directory with a ``last`` pointer (a run's
        ``checkpoints/``).
        """
        from mmf_rl.models.registry import load_trained_model

        model, stats, data_config = load_trained_model(path, map_location)
        return cls(model, stats, stride=int(data_config.get("stride", 1)), num_samples=num_samples,
                   denormalize=denormalize)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._check_modalities(observation_spec)
        batch = observation_spec.shape
        out = (*batch, self.horizon, self.target_dim)
        forecast = Composite(loc=Unbounded(out, dtype=torch.float32), scale=Unbounded(out, dtype=torch.float32),
                             valid=Categorical(2, batch, dtype=torch.bool), shape=batch)
        if self.num_samples:
            forecast[keys.SAMPLES] = Unbounded((*batch, self.num_samples, self.horizon, self.target_dim),
                                               dtype=torch.float32)
        observation_spec[keys.FORECAST] = forecast
        return observation_spec

    # -- forecast ------------------------------------------------------------------------------

    @torch.no_grad()
    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        window = self.window()
        n = window.batch_size[0]
        valid = torch.stack([window.get(s.present_key) for s in self.specs], 1).any(1)
        loc = torch.zeros(n, self.horizon, self.target_dim)
        scale = torch.ones(n, self.horizon, self.target_dim)
        samples = loc.unsqueeze(1).repeat(1, self.num_samples, 1, 1) if self.num_samples else None
        if valid.any():
            rows = None if valid.all() else valid.nonzero().squeeze(1)
            inputs = window if rows is None else window[rows]
            device = next(self.model.parameters()).device
            inputs = inputs.to(device)
            out = self.model(inputs.clone(False))
            predicted = [out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)]
            if self.num_samples:
                predicted.append(self.model.sample(inputs.clone(False), self.num_samples).get(keys.FORECAST_SAMPLES))
            targets = [loc, scale] + ([samples] if self.num_samples else [])
            for target, value in zip(targets, predicted):
                if rows is None:
                    target.copy_(value)
                else:
                    target[rows] = value.to(target.device)
        if self.denormalize:
            loc = self.normalizer.denormalize_target(loc)
            scale = self.normalizer.denormalize_target_scale(scale)
            if self.num_samples:
                samples = self.normalizer.denormalize_target(samples)
        batch = self._batch_size
        tensordict.set(keys.FORECAST_LOC, loc.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_SCALE, scale.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_VALID, valid.reshape(batch))
        if self.num_samples:
            tensordict.set(keys.FORECAST_SAMPLES,
                           samples.reshape(*batch, self.num_samples, self.horizon, self.target_dim))
        return tensordict



class HistoryWindow(_WindowTransform):
    """Writes each env's model input window into the observation, under ``"history"``.

    ``("history", "obs", m)`` ``[*batch, *window shape]`` and ``("history", "present", m)``
    ``bool [*batch]``: exactly a model batch of the `mmf_rl.keys` contract, built by the rules of
    `ForecastTransform` (normalised vectors, resized images, window presence). A policy reads it
    with ``tensordict.get("history")`` and runs any forecaster on it: this is how a planner
    conditions a world model on the real history (`mmf_rl.planning.SequenceCEMPlanner`).

    Args:
        specs: the model's modalities (``model.config.modalities``).
        stats: the normalisation statistics of its training run.
        history: ``H``, window steps.
        stride: frames between two window steps.
    """

    def __init__(self, specs: Sequence[ModalitySpec], stats: Mapping[str, torch.Tensor], history: int,
                 stride: int = 1):
        specs = list(specs)
        out_keys = [(keys.HISTORY, *s.obs_key) for s in specs] + [(keys.HISTORY, *s.present_key) for s in specs]
        super().__init__(specs, stats, history, stride, out_keys)

    @classmethod
    def for_model(cls, model: nn.Module, stats: Mapping[str, torch.Tensor], stride: int = 1) -> HistoryWindow:
        """The window ``model`` reads (its modalities and history)."""
        return cls(model.config.modalities, stats, model.config.history, stride)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._check_modalities(observation_spec)
        batch = observation_spec.shape
        observations = Composite(shape=batch)
        presence = Composite(shape=batch)
        for spec in self.specs:
            shape = (*batch, *spec.obs_shape(self.history))
            observations[spec.name] = (Bounded(0, 255, shape, dtype=torch.uint8) if spec.kind == "image"
                                       else Unbounded(shape, dtype=torch.float32))
            presence[spec.name] = Categorical(2, batch, dtype=torch.bool)
        observation_spec[keys.HISTORY] = Composite({keys.OBS: observations, keys.PRESENT: presence}, shape=batch)
        return observation_spec

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        window = self.window()
        tensordict.set(keys.HISTORY, window.reshape(self._batch_size))
        return tensordict
