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

import logging
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
from mmf_rl.models.forecaster import MultimodalForecaster
from mmf_rl.models.loading import load_trained_model
from mmf_rl.models.rows import compute_on_rows

logger = logging.getLogger(__name__)

# What to pass instead when a trained model's statistics lack some.
RUN_STATS_FIX = "pass the stats of the run that trained the model (checkpoint.tensors)"


def trained_per_step_presence(data_config: Mapping, requested: bool | None, owner: str) -> bool:
    """The ``per_step_presence`` of a transform serving a trained run: the run's
    ``data.partial_windows`` (``False`` for a run without the key: trained before it existed), so
    the windows' presence follows the rule the model was trained on; ``requested`` (not ``None``)
    overrides it, with a warning when it contradicts the training."""
    trained = bool(data_config.get("partial_windows", False))
    if requested is None:
        return trained
    if bool(requested) != trained:
        logger.warning(
            "%s: per_step_presence=%s, but the model was trained with data.partial_windows=%s; its windows "
            "will count a sensor lost for some steps %s, not as in training",
            owner,
            bool(requested),
            trained,
            "present (per-step presence)" if requested else "absent for the whole window",
        )
    return bool(requested)


def require_stats(owner: str, stats: Mapping[str, torch.Tensor], names: Sequence[str], fix: str) -> None:
    """Raise a KeyError naming ``owner``, the ``names`` that ``stats`` lacks and the ``fix``."""
    missing = [name for name in names if name not in stats]
    if missing:
        raise KeyError(f"{owner}: normalisation stats lack {missing} (found {sorted(stats)}); {fix}")


def _describe_spec(spec, batch_dims: int) -> str:
    """dtype and per-env shape of a leaf spec."""
    return f"{str(spec.dtype).removeprefix('torch.')} {list(spec.shape[batch_dims:])}"


class _WindowTransform(Transform):
    """Keeps each env's last ``(H - 1) * stride + 1`` frames of every modality in a ring buffer and
    builds the model's input window from them, as the data pipeline does (see `ForecastTransform`
    for the rules). Subclasses say what to write each step (:meth:`_emit`) and add its specs.

    The history is module state, as torchrl's ``CatFrames`` keeps its frames: buffers that follow
    ``.to(device)`` (so a step never copies it between host and device) and ``state_dict`` /
    ``load_state_dict`` (with the ring position and the env batch size, the module's extra state).
    The buffers are shaped by the env batch at the first reset; a state dict restores that shape.
    """

    def __init__(
        self,
        specs: Sequence[ModalitySpec],
        stats: Mapping[str, torch.Tensor],
        history: int,
        stride: int,
        out_keys: list,
        device: torch.device | str = "cpu",
        per_step_presence: bool = False,
    ):
        self.specs: list[ModalitySpec] = list(specs)
        if stride < 1:
            raise ValueError(f"{type(self).__name__}: stride must be >= 1, found {stride}")
        required = [f"{s.name}/{stat}" for s in self.specs if s.kind != "image" for stat in ("mean", "std")]
        require_stats(type(self).__name__, stats, [*required, "target/mean", "target/std"], RUN_STATS_FIX)
        in_keys = [s.obs_key for s in self.specs] + [s.present_key for s in self.specs]
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.history, self.stride = history, stride
        self.per_step_presence = per_step_presence
        self.buffer_length = (history - 1) * stride + 1
        # The statistics are the checkpoint's constants (not state): buffers for the device only.
        self._stat_names = sorted(stats)
        for i, name in enumerate(self._stat_names):
            self.register_buffer(f"_stat_{i}", stats[name].float().to(device), persistent=False)
        # Ring slots of the H window steps, oldest first, for each slot of the newest frame.
        steps = torch.arange(history - 1, -1, -1) * stride
        slots = torch.stack([(newest - steps) % self.buffer_length for newest in range(self.buffer_length)])
        self.register_buffer("_slots", slots.to(device), persistent=False)
        for i, spec in enumerate(self.specs):
            frames = torch.zeros(0, self.buffer_length, *spec.shape, dtype=spec.dtype, device=device)
            self.register_buffer(f"_frames_{i}", frames)
            self.register_buffer(
                f"_present_{i}", torch.zeros(0, self.buffer_length, dtype=torch.bool, device=device)
            )
        self._newest = 0  # ring slot of the newest frame, shared by all envs (a reset fills every slot)
        self._batch_size: torch.Size | None = None

    @property
    def normalizer(self) -> Normalizer:
        """The normalisation statistics of the model's training run, on the transform's device."""
        return Normalizer({name: getattr(self, f"_stat_{i}") for i, name in enumerate(self._stat_names)})

    # -- state ---------------------------------------------------------------------------------

    def _frames(self, i: int) -> torch.Tensor:
        """The ring buffer of modality ``i``'s frames, ``[n, buffer_length, *shape]``."""
        return getattr(self, f"_frames_{i}")

    def _presence(self, i: int) -> torch.Tensor:
        """The ring buffer of modality ``i``'s presence flags, ``[n, buffer_length]``."""
        return getattr(self, f"_present_{i}")

    def get_extra_state(self) -> dict:
        """What the history buffers need besides their values: the ring position and the env batch."""
        batch_size = None if self._batch_size is None else list(self._batch_size)
        return {"newest": self._newest, "batch_size": batch_size}

    def set_extra_state(self, state: dict) -> None:
        self._newest = int(state["newest"])
        batch_size = state["batch_size"]
        self._batch_size = None if batch_size is None else torch.Size(batch_size)
        self._batch_size_changed()

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # The buffers are shaped by the env batch of the saved transform: take its shape first.
        for name in [f"_{kind}_{i}" for kind in ("frames", "present") for i in range(len(self.specs))]:
            saved = state_dict.get(prefix + name)
            current = getattr(self, name)
            if saved is not None and saved.shape != current.shape:
                setattr(self, name, current.new_empty(saved.shape))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _batch_size_changed(self) -> None:
        """Called when the history is set up for a new env batch (at a reset or a state load)."""

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

    def _frame(
        self, spec: ModalitySpec, tensordict: TensorDictBase, n: int, normalizer: Normalizer
    ) -> torch.Tensor:
        """One step of ``spec`` for all envs, as the model's window stores it: ``[n, *shape]``."""
        try:
            value = tensordict.get(spec.obs_key)
        except KeyError:
            raise KeyError(
                f"{type(self).__name__}: the env output has no {spec.obs_key}; the model reads "
                f"{[s.obs_key for s in self.specs]}"
            ) from None
        value = value.to(self._slots.device)
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
        return normalizer.normalize(spec.name, value.reshape(n, *spec.shape).float())

    def _push(self, tensordict: TensorDictBase, rows: torch.Tensor | None) -> None:
        """Append this step's frame: to every env (``rows=None``), or fill the history of ``rows``."""
        n = self._batch_size.numel()
        if rows is None:
            self._newest = (self._newest + 1) % self.buffer_length
        normalizer = self.normalizer
        for i, spec in enumerate(self.specs):
            frame = self._frame(spec, tensordict, n, normalizer)
            present = tensordict.get(spec.present_key).reshape(n).to(frame.device)
            # A sensor reading NaN/Inf is absent for every window holding it, as in the data
            # pipeline: the model never sees it, so no forecast or action turns NaN. (One check
            # of the whole frame first: the rows are looked for only when one is unreadable.)
            if frame.is_floating_point() and not bool(torch.isfinite(frame).all()):
                unreadable = keys.nonfinite_rows(frame)
                frame = frame.masked_fill(unreadable.view(-1, *[1] * (frame.dim() - 1)), 0)
                present = present & ~unreadable
            if rows is None:
                self._frames(i)[:, self._newest] = frame
                self._presence(i)[:, self._newest] = present
            else:
                self._frames(i)[rows] = frame[rows].unsqueeze(1)
                self._presence(i)[rows] = present[rows].unsqueeze(1)

    def _allocate(self, batch_size: torch.Size) -> None:
        n, length = batch_size.numel(), self.buffer_length
        for i, spec in enumerate(self.specs):
            setattr(self, f"_frames_{i}", self._frames(i).new_zeros(n, length, *spec.shape))
            setattr(self, f"_present_{i}", self._presence(i).new_zeros(n, length))
        self._newest = 0
        self._batch_size = batch_size
        self._batch_size_changed()

    def window(self) -> TensorDict:
        """The model's input for every env, ``[n]`` (flattened env batch), as the data pipeline builds it."""
        observations, presence, steps = self._window_tensors()
        window = TensorDict(batch_size=[self._batch_size.numel()])
        for spec, values, present in zip(self.specs, observations, presence, strict=True):
            window.set(spec.obs_key, values)
            window.set(spec.present_key, present)
        for key, step_present in zip(self._step_keys, steps, strict=True):
            window.set(key, step_present)
        return window

    @property
    def _step_keys(self) -> list[tuple[str, str]]:
        """The ``("present_steps", m)`` keys the windows carry (windowed modalities, when per step)."""
        if not self.per_step_presence:
            return []
        return [keys.present_steps_key(s.name) for s in self.specs if s.kind != "vector"]

    def _window_tensors(self) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
        """:meth:`window` as plain tensors: observations and presence flags, one per modality, and
        the step presence ``[n, H]`` of each windowed modality (none unless ``per_step_presence``: a
        windowed modality is then present when present at one step at least, else at every step)."""
        slots = self._slots[self._newest]
        observations, presence, steps = [], [], []
        for i, spec in enumerate(self.specs):
            if spec.kind == "vector":
                values = self._frames(i)[:, self._newest]
                present = self._presence(i)[:, self._newest]
            else:
                values = self._frames(i).index_select(1, slots)
                step_present = self._presence(i).index_select(1, slots)
                present = step_present.any(1) if self.per_step_presence else step_present.all(1)
                if self.per_step_presence:
                    steps.append(step_present & present.unsqueeze(1))
                    values = keys.zero_absent_steps(values, steps[-1])
            if spec.kind != "image":
                values = values * present.view(-1, *[1] * (values.dim() - 1))
            observations.append(values)
            presence.append(present)
        return observations, presence, steps

    # -- env hooks -----------------------------------------------------------------------------

    def observe_reset(self, observation: TensorDictBase) -> TensorDictBase:
        """Fill every env's history with a reset's ``observation`` (env batch ``[*batch]``) and write
        this transform's output into it, as ``env.reset()`` does in a `TransformedEnv`: for a caller
        that steps an env of its own (the recorder's `mmf_rl.rl.agent.MPCActor`)."""
        return self._reset(observation.empty(), observation)

    def observe_step(self, observation: TensorDictBase) -> TensorDictBase:
        """Append a step's ``observation`` to every env's history and write this transform's output
        into it, as ``env.step()`` does in a `TransformedEnv` (see :meth:`observe_reset`)."""
        return self._call(observation)

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        rows = reset_rows(tensordict, batch_size, self._batch_size, type(self).__name__)
        if self._batch_size != batch_size:
            self._allocate(batch_size)
        self._push(tensordict_reset, rows.to(self._slots.device))
        return self._emit(tensordict_reset)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._batch_size is None:
            raise RuntimeError(
                f"{type(self).__name__}: the env was stepped before its first reset; call env.reset()"
            )
        if next_tensordict.batch_size != self._batch_size:
            raise RuntimeError(
                f"{type(self).__name__}: the env batch is {list(next_tensordict.batch_size)} but was "
                f"{list(self._batch_size)} at the last reset; reset every env after changing the batch size"
            )
        self._push(next_tensordict, None)
        return self._emit(next_tensordict)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise not_standalone(type(self).__name__)


class ForecastTransform(_WindowTransform):
    """Runs a trained forecaster on the last H steps of every env; writes ``("forecast", ...)``.

    Args:
        model (nn.Module): a forecaster from the model registry (``config.modalities``,
            ``config.history``, ``config.horizon``, ``config.target_dim``); it is put in eval mode and
            run without gradients. An action-conditioned world model cannot forecast without the
            future actions: plan with it instead (`HistoryWindow` + `mmf_rl.rl`).
        stats (Mapping[str, torch.Tensor]): the normalisation statistics of its training run (a
            checkpoint's ``tensors``): ``"<m>/mean"``, ``"<m>/std"`` for every non-image modality,
            ``"target/mean"``, ``"target/std"``.

    Keyword Args:
        stride (int, optional): frames between two window steps (the data config's ``stride``).
            Defaults to ``1``.
        per_step_presence (bool, optional): ``True`` keeps a windowed modality present while present at one
            step of the window at least, with ``("present_steps", m)`` marking its steps (the model masks the
            absent ones), instead of absent unless present at every step. Runs the eager forward. Default
            ``False`` here; `for_trained` / `from_checkpoint` follow the run's training.
        num_samples (int, optional): ``K > 0`` also writes ``("forecast", "samples")`` ``[*batch, K, T, D]``,
            one forecast per prior latent draw (costs a second, eager forward).
        denormalize (bool, optional): ``True`` (default) writes forecasts in the target's units (for the push
            data: metres, world frame; a run trained with ``data.target.relative`` forecasts displacements
            from the current step, as the push config does, one with ``data.target.relative_to`` offsets from
            a reference at the current step), ``False`` in the normalised frame the model was trained in.
        trace (bool, optional): ``True`` (the default) runs the paper's forecaster (`MultimodalForecaster`) as
            frozen `torch.jit.trace` graphs on plain tensors: the whole forecast when every env
            has every sensor, else one graph per modality encoder and one for the rest
            (:meth:`~MultimodalForecaster.forecast_from_tokens`: prior, latent, decoder). No
            TensorDict, validation or Python module dispatch per step (the inputs were checked
            against the env's specs once, :meth:`transform_observation_spec`), and no
            posterior. No graph branches on presence, so a sensor that dies or comes back runs
            graphs already traced or traces the missing ones once (at most M + 2 per batch
            size; a new batch size, at a reset, replaces them); the encoder of a modality no
            env has is skipped, and one present in some envs only runs eagerly on those (as the
            model's own encode). Each graph is traced on its first use (a step that takes a
            few hundred ms). An in-place update of the weights or the scale factors
            (``load_state_dict``, an optimizer step, a calibration fit) is detected and re-traces
            them. ``False``, and any other model, run
            the model's eager TensorDict forward; both write the same forecasts (to float
            rounding).

    Written every step (env batch ``[*batch]``): ``("forecast", "loc")`` and ``("forecast",
    "scale")`` ``float32 [*batch, T, D]`` (the model's deterministic eval forecast: the location and
    scale of its output family, a diagonal Gaussian by default), ``("forecast", "samples")`` when
    ``num_samples > 0``, and ``("forecast", "valid")`` ``bool [*batch]``.

    The window follows the data pipeline (`mmf_rl.datasets.windows`): vector observations are
    normalised with ``stats``; images are resized to the model's size the way the cache resizes
    them (bilinear, antialiased); a reading with NaN or ±Inf counts as absent at its step; a
    ``"sequence"``/``"image"`` modality is present in the window only if it is present at all H
    steps (with ``per_step_presence``: at one step at least; ``"vector"``: at the last step), and an
    absent modality's vector window is zeroed.
    After a reset, the first observation fills the whole history (its presence too), so a full
    window exists from the first step; it is replaced step by step over the next H-1 steps. A
    window with no present modality cannot be forecast: its row gets ``valid = False`` and the
    training marginal of the target (normalised mean 0, scale 1, i.e. ``target/mean`` and
    ``target/std`` in target units).

    The history is a fixed ring buffer per env: the cost per step does not grow with time
    (`benchmarks/forecast_transform_cost.py` measures it against the env step). It starts on the
    model's device; ``transform.to(device)`` moves the model, the history and the statistics
    together (buffers), so a step copies nothing but the env's observation onto that device, and
    ``state_dict`` carries the history of a running transform.

    A trained run's transform: ``ForecastTransform.from_checkpoint("runs/push/checkpoints")``. It
    keeps per-env state, so it only runs inside a `TransformedEnv`.

    Raises:
        ValueError: an action-conditioned model, ``num_samples < 0`` (or ``> 0`` for a model
            without ``sample``), ``stride < 1``, or (when appended to an env) an env that does not
            emit a modality the model reads, or emits it with another kind or shape.
        KeyError: ``stats`` lacks a modality's or the target's statistics.

    Examples:
        A forecaster on the simulated push env, behind its force sensor's outages:

        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mmf_rl.envs import ModalityDropout, MultimodalPushTorchEnv
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> proprio = ModalitySpec("proprio", "sequence", (17,))
        >>> sizes = dict(history=4, horizon=5, d_model=16, d_latent=4, num_heads=2)
        >>> model = MultimodalForecaster(ForecasterConfig([force, proprio], **sizes))  # untrained
        >>> stats = {  # its training run's normalisation statistics (a checkpoint's tensors)
        ...     "force/mean": torch.zeros(6), "force/std": torch.ones(6),
        ...     "proprio/mean": torch.zeros(17), "proprio/std": torch.ones(17),
        ...     "target/mean": torch.zeros(2), "target/std": torch.ones(2),
        ... }
        >>> from mmf_rl.rl import ForecastTransform
        >>> env = TransformedEnv(MultimodalPushTorchEnv(image_size=16), Compose(
        ...     ModalityDropout(["force"], outage_prob=0.5, seed=0),
        ...     ForecastTransform(model, stats),
        ... ))
        >>> rollout = env.rollout(3)
        >>> rollout["next", "forecast", "loc"].shape  # [steps, T, D], in the target's units
        torch.Size([3, 5, 2])
        >>> rollout["next", "present", "force"], rollout["next", "forecast", "valid"]
        (tensor([False, False, False]), tensor([True, True, True]))
        >>> env.close()
    """

    def __init__(
        self,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        *,
        stride: int = 1,
        num_samples: int = 0,
        denormalize: bool = True,
        trace: bool = True,
        per_step_presence: bool = False,
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
        device = next(model.parameters()).device
        super().__init__(
            config.modalities, stats, config.history, stride, out_keys, device, per_step_presence
        )
        self.model = model.eval()
        self.horizon, self.target_dim = config.horizon, config.target_dim
        self.num_samples, self.denormalize = num_samples, denormalize
        # The traced graphs take modality presence only: step masks go through the eager forward.
        self.trace = trace and not per_step_presence and isinstance(model, MultimodalForecaster)
        self._model_keys = [s.obs_key for s in self.specs] + [s.present_key for s in self.specs]
        self._model_keys += self._step_keys
        self._traced: _TracedForecaster | None = None  # for the current batch size

    @classmethod
    def from_checkpoint(
        cls, path: str | os.PathLike, *, map_location: str | torch.device = "cpu", **options
    ) -> ForecastTransform:
        """Load the model, its weights, normalisation stats and window stride from a checkpoint
        (`for_trained`, a subclass's too: `LatchedForecastTransform` adds its target frame).

        Args:
            path (str | os.PathLike): what `load_trained_model` reads: a run directory, its
                ``checkpoints/``, one checkpoint or a ``save_pretrained`` directory.

        Keyword Args:
            map_location (str | torch.device, optional): the model's device. Defaults to ``"cpu"``.
            **options: ``num_samples``, ``denormalize``, ``trace``, ``per_step_presence`` (a
                subclass's: also its own, e.g. ``latch_on``, ``rule``).

        Returns:
            The transform.
        """
        return cls.for_trained(*load_trained_model(path, map_location), **options)

    @classmethod
    def for_trained(
        cls,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        data_config: Mapping,
        *,
        per_step_presence: bool | None = None,
        **options,
    ) -> ForecastTransform:
        """The transform of a trained model (`load_trained_model`'s triple): the stride of its data
        config, and per-step presence as it was trained.

        Args:
            model (nn.Module): the trained model.
            stats (Mapping[str, torch.Tensor]): its normalisation statistics.
            data_config (Mapping): its data config (``stride``, ``partial_windows``).

        Keyword Args:
            per_step_presence (bool, optional): overrides the run's ``data.partial_windows`` (with a
                warning when it contradicts the training, `trained_per_step_presence`).
            **options: the other keyword arguments of the constructor.

        Returns:
            The transform.
        """
        options["per_step_presence"] = trained_per_step_presence(data_config, per_step_presence, cls.__name__)
        return cls(model, stats, stride=int(data_config.get("stride", 1)), **options)

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

    def _batch_size_changed(self) -> None:
        # Graphs are traced for one batch size: the previous ones go (memory stays bounded).
        batch_size = self._batch_size
        traced = self.trace and batch_size is not None
        self._traced = _TracedForecaster(self.model, self.specs, batch_size.numel()) if traced else None

    def _apply(self, fn, *args, **kwargs):
        module = super()._apply(fn, *args, **kwargs)
        # The graphs hold the weights as constants where they were traced: trace them again.
        self._batch_size_changed()
        return module

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        observations, presence, steps = self._window_tensors()
        present = torch.stack(presence, 1)
        presence = presence + steps  # the model's presence keys, in the order of _model_keys
        valid = present.any(1)
        if self._traced is not None:
            # No grad, not inference mode: a policy trained on the forecasts saves them for backward.
            with torch.no_grad():
                loc, scale = self._traced(observations, present, valid)
            samples = self._samples(observations, presence, valid) if self.num_samples else None
        else:
            loc, scale, *samples = self._eager(observations, presence, valid)
            samples = samples[0] if samples else None
        if self.denormalize:
            loc = self.normalizer.denormalize_target(loc)
            scale = self.normalizer.denormalize_target_scale(scale)
            if samples is not None:
                samples = self.normalizer.denormalize_target(samples)
        batch = self._batch_size
        tensordict.set(keys.FORECAST_LOC, loc.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_SCALE, scale.reshape(*batch, self.horizon, self.target_dim))
        tensordict.set(keys.FORECAST_VALID, valid.reshape(batch))
        if samples is not None:
            tensordict.set(
                keys.FORECAST_SAMPLES,
                samples.reshape(*batch, self.num_samples, self.horizon, self.target_dim),
            )
        return tensordict

    def _prior(self, n: int) -> list[torch.Tensor]:
        """The target's training prior (zero mean, unit scale) for ``n`` envs with no present sensor:
        ``loc``, ``scale``, and its samples (its mean) when ``num_samples > 0``."""
        shape, device = (n, self.horizon, self.target_dim), self._slots.device
        prior = [torch.zeros(shape, device=device), torch.ones(shape, device=device)]
        if self.num_samples:
            prior.append(torch.zeros(n, self.num_samples, *shape[1:], device=device))
        return prior

    def _eager(self, observations, presence, valid) -> tuple[torch.Tensor, ...]:
        """``loc``, ``scale`` (and the samples) of the model's eager TensorDict forward on the valid rows."""

        def predict(rows: torch.Tensor | None) -> list[torch.Tensor]:
            window = self._model_window(observations, presence, rows)
            with torch.inference_mode():
                out = self.model(window.clone(False))
                predicted = [out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)]
                if self.num_samples:
                    predicted.append(self.model.sample(window, self.num_samples).get(keys.FORECAST_SAMPLES))
            # Copied out of inference mode: a policy trained on the forecasts must be able to
            # save them for backward.
            return [p.clone() for p in predicted]

        return compute_on_rows(valid, predict, self._prior(valid.shape[0]))

    def _samples(self, observations, presence, valid) -> torch.Tensor:
        """``("forecast", "samples")`` in the model's frame, by its eager ``sample`` on the valid rows."""

        def sample(rows: torch.Tensor | None) -> list[torch.Tensor]:
            window = self._model_window(observations, presence, rows)
            with torch.no_grad():
                return [self.model.sample(window, self.num_samples).get(keys.FORECAST_SAMPLES)]

        return compute_on_rows(valid, sample, self._prior(valid.shape[0])[2:])[0]

    def _model_window(self, observations, presence, rows) -> TensorDict:
        inputs = [t if rows is None else t[rows] for t in observations + presence]
        return TensorDict(dict(zip(self._model_keys, inputs, strict=True)), batch_size=inputs[0].shape[:1])


class _TracedForecaster:
    """`MultimodalForecaster`'s eval forecast of ``n`` windows as frozen `torch.jit.trace` graphs,
    each traced on first use: the whole forecast when every modality is present in every row
    (the common case, one graph call per step), else one graph per modality encoder (on all
    ``n`` rows) and one for :meth:`~MultimodalForecaster.forecast_from_tokens`.

    The eager forward's forecasts (to float rounding) for every presence pattern, because no
    graph branches on presence: the first one serves a single pattern and is used for it only,
    an encoder sees one modality's rows, and the presence mask is an input of the last graph. The
    presence branches of the model's own
    ``encode`` are taken here in Python, the same way: a modality present nowhere gets zero
    tokens (its encoder does not run), one present in some rows only runs the eager encoder on
    those rows (`compute_on_rows`; no graph per row count, so there are at most M + 2 graphs
    however the outages fall).

    Frozen (``torch.jit.freeze``: the weights become constants of the graph, which spares a
    parameter lookup per use and folds what depends on weights only), so an in-place change of
    the model's parameters or buffers (``load_state_dict``, an optimizer step, fitting the scale
    factors) is caught by their version
    counters and the graphs are traced again. With ``eval_latent="sample"`` a latent is drawn for
    every row, where the eager forward draws for the rows with a sensor only: the same
    distribution, but other draws when some env has none.

    Why `torch.jit.trace`, deprecated in torch 2.x: torch.export refuses the presence branches
    of the whole forward, and ``torch.compile`` (inductor) compiled the image encoder alone for
    over a minute and ran it slower than this trace (see docs/results.md).
    """

    def __init__(self, model: MultimodalForecaster, specs: Sequence[ModalitySpec], n: int):
        self.model, self.specs, self.n = model, list(specs), n
        # Buffers too: the scale factors of `mmf-rl calibrate` are frozen into the graphs as well.
        self.tensors = list(model.parameters()) + list(model.buffers())
        self.version = self._weights_version()
        self.everywhere: torch.jit.ScriptModule | None = None
        self.encoders: dict[str, torch.jit.ScriptModule] = {}
        self.head: torch.jit.ScriptModule | None = None

    def __call__(
        self, observations: list[torch.Tensor], present: torch.Tensor, valid: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``loc``, ``scale`` ``[n, T, D]``: the model's, in rows with a present modality; in the
        others, the prior (zeros, ones: `ForecastTransform` denormalises it to the target's marginal)."""
        version = self._weights_version()
        if version != self.version:
            self.encoders.clear()
            self.everywhere, self.head, self.version = None, None, version
        if bool(present.all()):
            if self.everywhere is None:
                names = [s.name for s in self.specs]
                self.everywhere = _trace(_ForecastFromWindows(self.model, names), (present, *observations))
            return self.everywhere(present, *observations)
        counts = present.sum(0).tolist()  # envs with each modality: one sync for all the branches below
        tokens = []
        for i, (spec, obs, count) in enumerate(zip(self.specs, observations, counts, strict=True)):
            if count == self.n:
                token = self.model.as_tokens(self._encoder(spec.name, obs)(obs))
            else:
                zeros = self.model.absent_tokens(i, self.n, present.device)
                encoder = self.model.encoders[spec.name]
                token = compute_on_rows(
                    present[:, i],
                    lambda rows, obs=obs, e=encoder: (self.model.as_tokens(e(obs[rows])),),
                    (zeros,),
                )[0]
            tokens.append(token)
        tokens = torch.cat(tokens, 1)
        everywhere = bool(valid.all())
        if not everywhere:
            # Rows without any sensor are decoded on their zero tokens as if all were present (an
            # attention over no key is NaN); their forecast is replaced by the prior below.
            present = present | ~valid.unsqueeze(1)
        if self.head is None:
            self.head = _trace(_ForecastFromTokens(self.model), (tokens, present))
        loc, scale = self.head(tokens, present)
        if not everywhere:
            keep = valid.view(-1, 1, 1)
            loc, scale = loc.where(keep, 0.0), scale.where(keep, 1.0)
        return loc, scale

    def _encoder(self, name: str, example: torch.Tensor) -> torch.jit.ScriptModule:
        graph = self.encoders.get(name)
        if graph is None:
            graph = self.encoders[name] = _trace(self.model.encoders[name], (example,))
        return graph

    def _weights_version(self) -> int:
        # Every in-place write to a tensor bumps its version counter.
        return sum(t._version for t in self.tensors)

    def __getstate__(self) -> dict:
        # A graph does not pickle: a copy (a transform sent to a worker) traces its own when used.
        return self.__dict__ | {"everywhere": None, "encoders": {}, "head": None}


class _ForecastFromWindows(nn.Module):
    """The eval forecast of windows with every modality present in every row: each encoder on its
    windows, then `MultimodalForecaster.forecast_from_tokens` (a module, for `torch.jit.trace`)."""

    def __init__(self, model: MultimodalForecaster, names: list[str]):
        super().__init__()
        self.model, self.names = model, names

    def forward(
        self, present: torch.Tensor, *observations: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        encoders, as_tokens = self.model.encoders, self.model.as_tokens
        tokens = torch.cat(
            [as_tokens(encoders[m](obs)) for m, obs in zip(self.names, observations, strict=True)], 1
        )
        return self.model.forecast_from_tokens(tokens, present[:, self.model.token_modality])


class _ForecastFromTokens(nn.Module):
    """`MultimodalForecaster.forecast_from_tokens` as a module (what `torch.jit.trace` takes)."""

    def __init__(self, model: MultimodalForecaster):
        super().__init__()
        self.model = model

    def forward(self, tokens: torch.Tensor, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``present``: modality presence ``[n, M]``, spread to the model's token presence."""
        return self.model.forecast_from_tokens(tokens, present[:, self.model.token_modality])


def _trace(module: nn.Module, example: tuple[torch.Tensor, ...]) -> torch.jit.ScriptModule:
    """A frozen `torch.jit.trace` of an eval-mode ``module`` (see `_TracedForecaster`)."""
    with torch.inference_mode(False), torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # torch.jit.trace (see _TracedForecaster)
        # The tracer warns of every Python branch on a tensor; in these modules they are on shapes
        # (attention and group-norm checks), fixed for the batch size the graphs are traced for.
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        traced = torch.jit.trace(module.eval(), tuple(t.clone() for t in example), check_trace=False)
        return torch.jit.freeze(traced)


class HistoryWindow(_WindowTransform):
    """Writes each env's model input window into the observation, under ``"history"``.

    ``("history", "obs", m)`` ``[*batch, *window shape]`` and ``("history", "present", m)``
    ``bool [*batch]``: exactly a model batch of the `mmf_rl.keys` contract, built by the rules of
    `ForecastTransform` (normalised vectors, resized images, window presence). A policy reads it
    with ``tensordict.get("history")`` and runs any forecaster on it: this is how a planner
    conditions a world model on the real history (`mmf_rl.rl.SequenceCEMPlanner`).

    Args:
        specs (Sequence[ModalitySpec]): the model's modalities (``model.config.modalities``).
        stats (Mapping[str, torch.Tensor]): the normalisation statistics of its training run.
        history (int): ``H``, window steps.
        stride (int, optional): frames between two window steps. Defaults to ``1``.
        per_step_presence (bool, optional): ``True`` also writes ``("history", "present_steps", m)``
            ``bool [*batch, H]`` of each windowed modality, present when present at one step at least.
            Defaults to ``False``.

    Raises:
        ValueError: ``stride < 1``, or (when appended to an env) an env that does not emit a modality
            of ``specs``, or emits it with another kind or shape.
        KeyError: ``stats`` lacks a modality's or the target's statistics.

    Examples:
        >>> import torch
        >>> from torchrl.envs import Compose, TransformedEnv
        >>> from mmf_rl.envs import ModalityDropout, MultimodalPushTorchEnv
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> proprio = ModalitySpec("proprio", "sequence", (17,))
        >>> sizes = dict(history=4, horizon=5, d_model=16, d_latent=4, num_heads=2)
        >>> model = MultimodalForecaster(ForecasterConfig([force, proprio], **sizes))  # untrained
        >>> stats = {  # its training run's normalisation statistics (a checkpoint's tensors)
        ...     "force/mean": torch.zeros(6), "force/std": torch.ones(6),
        ...     "proprio/mean": torch.zeros(17), "proprio/std": torch.ones(17),
        ...     "target/mean": torch.zeros(2), "target/std": torch.ones(2),
        ... }
        >>> from mmf_rl.rl import HistoryWindow
        >>> env = TransformedEnv(MultimodalPushTorchEnv(image_size=16), HistoryWindow.for_model(model, stats))
        >>> window = env.rollout(3)["next", "history"]  # a model batch, one per step
        >>> window["obs", "force"].shape, window["present", "proprio"]
        (torch.Size([3, 4, 6]), tensor([True, True, True]))
        >>> model.eval()(window[-1:].clone())["forecast", "loc"].shape
        torch.Size([1, 5, 2])
        >>> env.close()
    """

    def __init__(
        self,
        specs: Sequence[ModalitySpec],
        stats: Mapping[str, torch.Tensor],
        history: int,
        stride: int = 1,
        per_step_presence: bool = False,
    ):
        specs = list(specs)
        out_keys = [(keys.HISTORY, *s.obs_key) for s in specs] + [
            (keys.HISTORY, *s.present_key) for s in specs
        ]
        if per_step_presence:
            out_keys += [(keys.HISTORY, keys.PRESENT_STEPS, s.name) for s in specs if s.kind != "vector"]
        super().__init__(specs, stats, history, stride, out_keys, per_step_presence=per_step_presence)

    @classmethod
    def for_model(
        cls,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        stride: int = 1,
        per_step_presence: bool = False,
    ) -> HistoryWindow:
        """The window ``model`` reads (its modalities and history).

        Args:
            model (nn.Module): a model of the registry.
            stats (Mapping[str, torch.Tensor]): its normalisation statistics.
            stride (int, optional): its data's stride. Defaults to ``1``.
            per_step_presence (bool, optional): as its run was trained (``data.partial_windows``,
                `trained_per_step_presence`). Defaults to ``False``.

        Returns:
            The transform.
        """
        return cls(model.config.modalities, stats, model.config.history, stride, per_step_presence)

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
        history = {keys.OBS: observations, keys.PRESENT: presence}
        if self.per_step_presence:
            history[keys.PRESENT_STEPS] = Composite(
                {k[1]: Categorical(2, (*batch, self.history), dtype=torch.bool) for k in self._step_keys},
                shape=batch,
            )
        observation_spec[keys.HISTORY] = Composite(history, shape=batch)
        return observation_spec

    def _emit(self, tensordict: TensorDictBase) -> TensorDictBase:
        window = self.window()
        tensordict.set(keys.HISTORY, window.reshape(self._batch_size))
        return tensordict
