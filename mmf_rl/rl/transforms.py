"""TorchRL transforms that run a trained forecaster on a live multimodal env.

Both keep a rolling history of the last H steps of the `mmf_rl.keys` contract per env (shaped by
the env's batch size, so they work on a single env and on `SerialEnv`/`ParallelEnv` alike):

* `ForecastTransform`: a trained forecaster run on the history every step (one batched forward
  over all envs), the forecast written to ``("forecast", ...)``.
* `HistoryWindow`: the same rolling history, written as a model batch under ``"history"`` for a
  policy that runs its own model on it (a planner with a world model).

Put the simulated outages (`mmf_rl.envs.ModalityDropout`) before the forecaster::

    env = TransformedEnv(SerialEnv(4, make_env), Compose(
        ModalityDropout(["image", "force"], outage_prob=0.05, bursts=UniformBursts(3, 10), seed=0),
        ForecastTransform.from_checkpoint("runs/push/checkpoints"),
    ))
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import Transform

from mmf_rl import keys
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.envs.modality_dropout import not_standalone, reset_rows
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.registry import load_trained_model
from mmf_rl.models.rows import compute_on_rows


def _describe_spec(spec, batch_dims: int) -> str:
    """dtype and per-env shape of a leaf spec."""
    return f"{str(spec.dtype).removeprefix('torch.')} {list(spec.shape[batch_dims:])}"


class _WindowTransform(Transform):
    """Keeps each env's last ``(H - 1) * stride + 1`` frames of every modality in a ring buffer and
    builds the model's input window from them, as the data pipeline does (see `ForecastTransform`
    for the rules). Subclasses say what to write each step (:meth:`_emit`) and add its specs.
    """

    def __init__(
        self,
        specs: Sequence[ModalitySpec],
        stats: Mapping[str, torch.Tensor],
        history: int,
        stride: int,
        out_keys: list,
    ):
        self.specs: list[ModalitySpec] = list(specs)
        if stride < 1:
            raise ValueError(f"{type(self).__name__}: stride must be >= 1, found {stride}")
        required = [f"{s.name}/{stat}" for s in self.specs if s.kind != "image" for stat in ("mean", "std")]
        missing = [k for k in required + ["target/mean", "target/std"] if k not in stats]
        if missing:
            raise KeyError(
                f"{type(self).__name__}: normalisation stats lack {missing} (found {sorted(stats)}); "
                "pass the stats of the run that trained the model (checkpoint.tensors)"
            )
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
        env_side = {
            k[1]: observation_spec[k]
            for k in observation_spec.keys(True, True)
            if isinstance(k, tuple) and len(k) == 2 and k[0] == keys.OBS
        }
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
                    problems.append(
                        f"{spec.name!r} is {_describe_spec(found, batch_dims)}, expected uint8 "
                        f"[{spec.shape[0]}, h, w]"
                    )
            elif not found.dtype.is_floating_point or tuple(found.shape[-1:]) != spec.shape:
                problems.append(
                    f"{spec.name!r} is {_describe_spec(found, batch_dims)}, expected float {list(spec.shape)}"
                )
        if problems:
            model_side = ", ".join(f"{s.name} ({s.kind} {list(s.shape)})" for s in self.specs)
            env_listing = ", ".join(
                f"{name} ({_describe_spec(s, batch_dims)})" for name, s in sorted(env_side.items())
            )
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
            raise KeyError(
                f"{type(self).__name__}: the env output has no {spec.obs_key}; the model reads "
                f"{[s.obs_key for s in self.specs]}"
            ) from None
        if spec.kind == "image":
            value = value.reshape(n, *value.shape[-3:])
            if tuple(value.shape[-2:]) != spec.shape[-2:]:
                # As the window cache resizes decoded frames (mmf_rl.datasets.lerobot_source).
                value = F.interpolate(
                    value.float() / 255,
                    size=spec.shape[-2:],
                    mode="bilinear",
                    antialias=True,
                    align_corners=False,
                )
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
            # A sensor reading NaN/Inf is absent for every window holding it, as in the data
            # pipeline: the model never sees it, so no forecast or action turns NaN.
            unreadable = keys.nonfinite_rows(frame)
            if bool(unreadable.any()):
                frame = frame.masked_fill(unreadable.view(-1, *[1] * (frame.dim() - 1)), 0)
                present = present & ~unreadable
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
        observations, presence = self._window_tensors()
        window = TensorDict(batch_size=[self._batch_size.numel()])
        for spec, values, present in zip(self.specs, observations, presence, strict=True):
            window.set(spec.obs_key, values)
            window.set(spec.present_key, present)
        return window

    def _window_tensors(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """:meth:`window` as plain tensors, one per modality: observations and presence flags."""
        # Ring slots of the H window steps, oldest first.
        steps = torch.arange(self.history - 1, -1, -1) * self.stride
        slots = (self._newest - steps) % self.buffer_length
        observations, presence = [], []
        for spec in self.specs:
            if spec.kind == "vector":
                values = self._frames[spec.name][:, self._newest]
                present = self._present[spec.name][:, self._newest]
            else:
                values = self._frames[spec.name].index_select(1, slots)
                present = self._present[spec.name].index_select(1, slots).all(1)
            if spec.kind != "image":
                values = values * present.view(-1, *[1] * (values.dim() - 1))
            observations.append(values)
            presence.append(present)
        return observations, presence

    # -- env hooks -----------------------------------------------------------------------------

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        rows = reset_rows(tensordict, batch_size, self._batch_size, type(self).__name__)
        if self._batch_size != batch_size:
            self._allocate(batch_size)
        self._push(tensordict_reset, rows)
        return self._emit(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._batch_size is None:
            raise RuntimeError(
                f"{type(self).__name__}: the env was stepped before its first reset; call env.reset()"
            )
        self._push(next_tensordict, None)
        return self._emit(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise not_standalone(type(self).__name__)


class ForecastTransform(_WindowTransform):
    """Runs a trained forecaster on the last H steps of every env; writes ``("forecast", ...)``.

    Args:
        model: a forecaster from the model registry (``config.modalities``, ``config.history``,
            ``config.horizon``, ``config.target_dim``); it is put in eval mode and run under
            ``torch.inference_mode()``. An action-conditioned world model cannot forecast without the
            future actions: plan with it instead (`HistoryWindow` + `mmf_rl.rl`).
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
        trace: ``True`` runs a `torch.jit.trace` of the model's forward, one graph per
            batch size and presence pattern (traced the first time it occurs), on plain tensors:
            no TensorDict, validation or Python module dispatch per step. The inputs were checked
            against the env's specs once (:meth:`transform_observation_spec`). A batch where a
            modality is present in some envs but not others runs the eager forward, as does
            ``trace=False`` (for a model whose forward branches on values, which no registry
            model does: they branch on presence and shapes only). Off by default: with it, the
            resident memory of 16 envs under outages kept growing after warm-up (+56 MiB over 500
            steps, +68 MiB over 1000; flat without it), and its speed-up is not yet measured on a
            quiet machine.

    Written every step (env batch ``[*batch]``): ``("forecast", "loc")`` and ``("forecast",
    "scale")`` ``float32 [*batch, T, D]`` (the model's deterministic eval forecast, a diagonal
    Gaussian), ``("forecast", "samples")`` when ``num_samples > 0``, and ``("forecast",
    "valid")`` ``bool [*batch]``.

    The window follows the data pipeline (`mmf_rl.datasets.windows`): vector observations are
    normalised with ``stats``; images are resized to the model's size the way the cache resizes
    them (bilinear, antialiased); a reading with NaN or ±Inf counts as absent at its step; a
    ``"sequence"``/``"image"`` modality is present in the window only if it is present at all H
    steps (``"vector"``: at the last step), and an absent modality's vector window is zeroed.
    After a reset, the first observation fills the whole history (its presence too), so a full
    window exists from the first step; it is replaced step by step over the next H-1 steps. A window with no present modality cannot be forecast: its
    row gets ``valid = False`` and the training marginal of the target (normalised mean 0,
    scale 1, i.e. ``target/mean`` and ``target/std`` in target units).

    The history is a fixed ring buffer per env: the cost per step does not grow with time
    (`benchmarks/forecast_transform_cost.py` measures it against the env step).
    """

    def __init__(
        self,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        *,
        stride: int = 1,
        num_samples: int = 0,
        denormalize: bool = True,
        trace: bool = False,
    ):
        config = model.config
        if getattr(config, "action_dim", 0):
            raise ValueError(
                "ForecastTransform: this model is an action-conditioned world model (action_dim="
                f"{config.action_dim}); it forecasts only under given future actions. Plan with it: "
                "HistoryWindow + mmf_rl.rl.SequenceCEMPlanner, or ForecasterWorldModelEnv"
            )
        if num_samples < 0:
            raise ValueError(f"ForecastTransform: num_samples must be >= 0, found {num_samples}")
        if num_samples and not hasattr(model, "sample"):
            raise ValueError(
                f"ForecastTransform: {type(model).__name__} has no latent to sample; use num_samples=0"
            )
        out_keys = [keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.FORECAST_VALID]
        if num_samples:
            out_keys.append(keys.FORECAST_SAMPLES)
        super().__init__(config.modalities, stats, config.history, stride, out_keys)
        self.model = model.eval()
        self.horizon, self.target_dim = config.horizon, config.target_dim
        self.num_samples, self.denormalize, self.trace = num_samples, denormalize, trace
        self._model_keys = [s.obs_key for s in self.specs] + [s.present_key for s in self.specs]
        self._graphs: dict[tuple, torch.jit.ScriptModule] = {}  # by presence pattern (_presence_pattern)

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        *,
        num_samples: int = 0,
        denormalize: bool = True,
        trace: bool = False,
        map_location: str | torch.device = "cpu",
    ) -> ForecastTransform:
        """Load the model, its weights, normalisation stats and window stride from a checkpoint.

        ``path``: a checkpoint directory or a directory with a ``last`` pointer (a run's
        ``checkpoints/``).
        """
        model, stats, data_config = load_trained_model(path, map_location)
        return cls(
            model,
            stats,
            stride=int(data_config.get("stride", 1)),
            num_samples=num_samples,
            denormalize=denormalize,
            trace=trace,
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        self._check_modalities(observation_spec)
        batch = observation_spec.shape
        out = (*batch, self.horizon, self.target_dim)
        forecast = Composite(
            loc=Unbounded(out, dtype=torch.float32),
            scale=Unbounded(out, dtype=torch.float32),
            valid=Categorical(2, batch, dtype=torch.bool),
            shape=batch,
        )
        if self.num_samples:
            forecast[keys.SAMPLES] = Unbounded(
                (*batch, self.num_samples, self.horizon, self.target_dim), dtype=torch.float32
            )
        observation_spec[keys.FORECAST] = forecast
        return observation_spec

    # -- forecast ------------------------------------------------------------------------------

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        observations, presence = self._window_tensors()
        n = self._batch_size.numel()
        valid = torch.stack(presence, 1).any(1)
        # Envs with no present sensor get the target's training prior (zero mean, unit scale).
        prior = [torch.zeros(n, self.horizon, self.target_dim), torch.ones(n, self.horizon, self.target_dim)]
        if self.num_samples:
            prior.append(torch.zeros(n, self.num_samples, self.horizon, self.target_dim))
        device = next(self.model.parameters()).device

        def predict(rows: torch.Tensor | None) -> list[torch.Tensor]:
            with torch.inference_mode():
                inputs = [(t if rows is None else t[rows]).to(device) for t in observations + presence]
                predicted = list(self._forecast(inputs))
                if self.num_samples:
                    window = TensorDict(
                        dict(zip(self._model_keys, inputs, strict=True)), batch_size=inputs[0].shape[:1]
                    )
                    predicted.append(self.model.sample(window, self.num_samples).get(keys.FORECAST_SAMPLES))
            # Copied out of inference mode: a policy trained on the forecasts must be able to
            # save them for backward.
            return [p.to("cpu", copy=True) for p in predicted]

        loc, scale, *samples = compute_on_rows(valid, predict, prior)
        samples = samples[0] if samples else None
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
            tensordict.set(
                keys.FORECAST_SAMPLES,
                samples.reshape(*batch, self.num_samples, self.horizon, self.target_dim),
            )
        return tensordict

    def _forecast(self, inputs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """``loc``, ``scale`` of the model's eval forecast for window tensors (observations, then presence).

        With ``trace``, a traced graph of the model's forward for this batch size and presence
        pattern (traced on first use); eagerly through the TensorDict forward otherwise, and for a
        batch where some modality is present in some rows only.
        """
        pattern = self._presence_pattern(inputs[len(self.specs) :]) if self.trace else None
        if pattern is None:
            out = self.model(
                TensorDict(dict(zip(self._model_keys, inputs, strict=True)), batch_size=inputs[0].shape[:1])
            )
            return out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)
        graph = self._graphs.get(pattern)
        if graph is None:
            graph = self._graphs[pattern] = self._trace(inputs)
        return graph(*inputs)

    @staticmethod
    def _presence_pattern(presence: list[torch.Tensor]) -> tuple | None:
        """(batch size, each modality present in every row or in none); ``None`` for a mixed column.

        The models take Python branches on presence (which encoders run, `compute_on_rows`) and
        on shapes, never on values: a trace is exact for the pattern it was traced with.
        """
        columns = []
        for present in presence:
            everywhere = bool(present.all())
            if not everywhere and bool(present.any()):
                return None
            columns.append(everywhere)
        return (presence[0].shape[0], *columns)

    def _trace(self, inputs: list[torch.Tensor]) -> torch.jit.ScriptModule:
        # Plain tensors in, (loc, scale) out: the graph has no TensorDict, validation or Python
        # dispatch left, and the outputs nobody reads (the posterior, in eval) are pruned from it.
        # Why torch.jit.trace, deprecated in torch 2.x: torch.export refuses the presence branches,
        # and torch.compile took minutes to compile on 2 CPU cores and was slower than this trace
        # at batch 1 (graph breaks around the TensorDict forward).
        with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
            # The trace freezes the presence branches: expected, hence keyed by presence pattern.
            warnings.simplefilter("ignore", torch.jit.TracerWarning)
            warnings.simplefilter("ignore", DeprecationWarning)
            example = tuple(t.clone() for t in inputs)
            return torch.jit.trace(
                _ForecastOfTensors(self.model, self._model_keys), example, check_trace=False
            )


class _ForecastOfTensors(nn.Module):
    """A forecaster's eval forward as a function of plain tensors (for `torch.jit.trace`)."""

    def __init__(self, model: nn.Module, in_keys: list):
        super().__init__()
        self.model, self.in_keys = model, in_keys

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = self.model(
            TensorDict(dict(zip(self.in_keys, tensors, strict=True)), batch_size=tensors[0].shape[:1])
        )
        return out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)


class HistoryWindow(_WindowTransform):
    """Writes each env's model input window into the observation, under ``"history"``.

    ``("history", "obs", m)`` ``[*batch, *window shape]`` and ``("history", "present", m)``
    ``bool [*batch]``: exactly a model batch of the `mmf_rl.keys` contract, built by the rules of
    `ForecastTransform` (normalised vectors, resized images, window presence). A policy reads it
    with ``tensordict.get("history")`` and runs any forecaster on it: this is how a planner
    conditions a world model on the real history (`mmf_rl.rl.SequenceCEMPlanner`).

    Args:
        specs: the model's modalities (``model.config.modalities``).
        stats: the normalisation statistics of its training run.
        history: ``H``, window steps.
        stride: frames between two window steps.
    """

    def __init__(
        self, specs: Sequence[ModalitySpec], stats: Mapping[str, torch.Tensor], history: int, stride: int = 1
    ):
        specs = list(specs)
        out_keys = [(keys.HISTORY, *s.obs_key) for s in specs] + [
            (keys.HISTORY, *s.present_key) for s in specs
        ]
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
            observations[spec.name] = (
                Bounded(0, 255, shape, dtype=torch.uint8)
                if spec.kind == "image"
                else Unbounded(shape, dtype=torch.float32)
            )
            presence[spec.name] = Categorical(2, batch, dtype=torch.bool)
        observation_spec[keys.HISTORY] = Composite(
            {keys.OBS: observations, keys.PRESENT: presence}, shape=batch
        )
        return observation_spec

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        window = self.window()
        tensordict.set(keys.HISTORY, window.reshape(self._batch_size))
        return tensordict
