"""A behaviour-cloning policy for the push task that can read the forecaster's forecast.

The forecaster's second use in RL, beside world models: a predictive module whose output is part
of a policy's observation. `BCPolicy` is a `TensorDictModule` that maps the env's observation to
an action in ``[-1, 1]``:

* the sensor windows `HistoryWindow` writes (``("history", "obs", m)``) and their presence
  flags (``("history", "present", m)``): each modality is encoded on the rows where it is
  present (the project's registered encoders: a ConvNet over the stacked frames, a flattened-
  window MLP for vectors) and contributes zeros where it is absent, followed by its flag, so the
  policy sees an outage and nothing of what the absent sensor held;
* the goal (``"goal"``, normalised), which a FetchPush policy is always given;
* with ``forecast_shape``: ``("forecast", "loc")`` and the log of ``("forecast", "scale")``,
  the object's motion over the next T steps as a trained forecaster sees it from the present
  sensors (`ForecastTransform` with ``denormalize=False``: the forecaster's normalised frame);
* with ``forecast_steps`` n: only the first n of those T steps (and their scales): where the
  object is about to be, without the rest of the forecast's motion, which restates what the
  demonstrator was about to do and so invites the policy to copy it;
* with ``latched_forecast`` (a rule, off by default): that forecast as a
  `LatchedForecastTransform` serves it through a camera outage, and ``log(1 + age)`` of
  ``("forecast", "age")``; trained on a `LatchedForecastTable`;
* with ``privileged_object`` (a diagnostic, not a deployable policy): the object's true planar
  position (x, y of ``"object_pose"``, normalised), fed like the goal: it tells whether locating
  the object from the sensors is what limits the policy. The position only: the scripted pusher
  the policy imitates steers by it and never reads the orientation, and the height is the table's.

A torchrl `MLP` maps the concatenation to the action (``tanh``). It is trained offline on the
recorded demonstrations (`mmf_rl.rl.demonstrations`) with torchrl's `BCLoss` (mean squared error
to the demonstrated action) and the project's `Trainer` (checkpoints: safetensors weights, the
config in ``meta.json``, the normalisation statistics beside them; resumable). Training removes
sensors at random per sample (``dropout``), so the policy has seen outages before it meets one;
the policy that reads forecasts is trained on the forecasts made under the same outages. Or each
sample's outage is drawn by an `OutageSampler` (``outages``), e.g. replays of the env's own outage
processes through the transforms the policy reads (``benchmarks/push/replayed_outages.py``).

With ``action_chunk`` k > 1 (`BCConfig`; default 1, the per-step policy) the network predicts the
next k actions (``"action_chunk"``), trained on the demonstrator's next k actions of the episode
(`mmf_rl.rl.action_chunks.ActionChunkLoss`, the steps past the episode's end masked out), and the
policy acts with ACT's temporal ensemble of its past chunks (`TemporalEnsemble`), whose state
lives in the tensordict: `BCPolicy.transforms` then adds an `InitTracker` and the state's primer.

A policy with another action head subclasses `BCPolicy` (its network, ``out_keys``, the ``mode``
that turns the head's output into the action, its `loss`, its config), as the push experiment's
Gaussian-mixture head does (``benchmarks/push/gmm_head.py``, measured not to help there).

In an env, the policy reads what its transforms write; put `ModalityDropout` before them::

    policy = BCPolicy.from_checkpoint("runs/bc/checkpoints")
    forecast = ForecastTransform.from_checkpoint("runs/push/checkpoints", denormalize=False)
    env = TransformedEnv(MultimodalPushTorchEnv(), Compose(
        ModalityDropout(["image"], outage="episode", outage_prob=1.0), *policy.transforms(forecast)))
    rollout = env.rollout(50, policy)
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import InitTracker
from torchrl.modules import MLP
from torchrl.objectives import BCLoss

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError, load_checkpoint, load_model_state, save_checkpoint
from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.encoders import build_encoder
from mmf_rl.models.rows import compute_on_rows
from mmf_rl.rl.action_chunks import ACTION_CHUNK, ActionChunkLoss, TemporalEnsemble
from mmf_rl.rl.demonstrations import (
    ACTION,
    OBJECT_PLANAR_DIMS,
    OBJECT_POSITION,
    DemonstrationLoader,
    Demonstrations,
    ForecastTable,
    OutageSampler,
    drop_sets,
)
from mmf_rl.rl.latched_forecast import RULES, LatchedForecastTable, LatchedForecastTransform
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow, require_stats
from mmf_rl.trainers.trainer import Trainer, TrainerConfig

# Training outages, the same for a policy with and without forecasts: each sample loses the
# camera and the force sensor independently with this probability (proprioception, the robot's
# own joint readings, is never removed).
DEFAULT_DROPOUT = {"image": 0.3, "force": 0.3}


@dataclass
class BCConfig:
    """What a `BCPolicy` reads and its sizes.

    Args:
        modalities (list[ModalitySpec]): the sensor windows (their ``encoder`` and ``encoder_kwargs``
            are the policy's own).
        history (int): the window's steps (`HistoryWindow`).
        stride (int, optional): frames between two window steps. Defaults to ``1``.
        goal_dim (int, optional): dims of the goal. Defaults to ``3``.
        action_dim (int, optional): dims of the action. Defaults to ``4``.
        forecast_shape (tuple[int, int], optional): ``(T, D)`` of the forecast input; ``None``: a policy
            without it.
        forecast_steps (int, optional): the first n of its T steps the policy reads (``None``: all).
        latched_forecast (str, optional): the rule of the `LatchedForecastTransform` whose forecast and
            age it reads (``None``: a `ForecastTransform`'s forecast, no age).
        privileged_object (bool, optional): the policy also reads the object's true planar position
            (privileged state, never removed by an outage: a diagnostic of what limits the policy, not
            a policy to deploy). Defaults to ``False``.
        d_model (int, optional): size of each modality's embedding. Defaults to ``64``.
        hidden (int, optional): the MLP head's width. Defaults to ``256``.
        depth (int, optional): the MLP head's number of hidden layers. Defaults to ``2``.
        action_chunk (int, optional): k, the actions predicted per step (1, the default: one, the
            per-step policy; k > 1: a chunk executed with temporal ensembling, `TemporalEnsemble`).
        chunk_decay (float, optional): the ensemble's ``m`` (ACT's weights ``exp(-m·i)``, ``i = 0`` the
            oldest prediction). Defaults to ``0.01``.

    Raises:
        ValueError: ``latched_forecast`` without a forecast input or outside the rules,
            ``forecast_steps`` outside ``1..T``, ``action_chunk < 1`` or a negative ``chunk_decay``.
    """

    modalities: list[ModalitySpec]
    history: int
    stride: int = 1
    goal_dim: int = 3
    action_dim: int = 4
    forecast_shape: tuple[int, int] | None = None
    forecast_steps: int | None = None
    latched_forecast: str | None = None
    privileged_object: bool = False
    d_model: int = 64
    hidden: int = 256
    depth: int = 2
    action_chunk: int = 1
    chunk_decay: float = 0.01

    def __post_init__(self):
        self.modalities = [
            m if isinstance(m, ModalitySpec) else ModalitySpec.from_dict(m) for m in self.modalities
        ]
        if self.forecast_shape is not None:
            self.forecast_shape = tuple(int(s) for s in self.forecast_shape)
        if self.latched_forecast is not None and self.forecast_shape is None:
            raise ValueError("BCConfig: latched_forecast needs a forecast input (forecast_shape)")
        if self.forecast_steps is not None and not (
            self.forecast_shape is not None and 1 <= self.forecast_steps <= self.forecast_shape[0]
        ):
            horizon = None if self.forecast_shape is None else self.forecast_shape[0]
            raise ValueError(
                f"BCConfig: forecast_steps must be between 1 and the forecast's horizon ({horizon}; None: no "
                f"forecast input), found {self.forecast_steps}"
            )
        if self.latched_forecast not in (None, *RULES):
            raise ValueError(
                f"BCConfig: latched_forecast must be one of {list(RULES)} or None, found "
                f"{self.latched_forecast!r}"
            )
        if self.action_chunk < 1 or not self.chunk_decay >= 0:
            raise ValueError(
                f"BCConfig: action_chunk must be >= 1 and chunk_decay >= 0, found {self.action_chunk}, "
                f"{self.chunk_decay}"
            )

    def to_dict(self) -> dict:
        """The config as plain data, what :meth:`from_dict` reads back (a checkpoint stores it)."""
        return {
            "modalities": [m.to_dict() for m in self.modalities],
            "history": self.history,
            "stride": self.stride,
            "goal_dim": self.goal_dim,
            "action_dim": self.action_dim,
            "forecast_shape": None if self.forecast_shape is None else list(self.forecast_shape),
            "forecast_steps": self.forecast_steps,
            "latched_forecast": self.latched_forecast,
            "privileged_object": self.privileged_object,
            "d_model": self.d_model,
            "hidden": self.hidden,
            "depth": self.depth,
            "action_chunk": self.action_chunk,
            "chunk_decay": self.chunk_decay,
        }

    @property
    def forecast_read_shape(self) -> tuple[int, int] | None:
        """``(n, D)``: the part of each forecast the policy reads (``None``: no forecast input)."""
        if self.forecast_shape is None:
            return None
        return (self.forecast_steps or self.forecast_shape[0], self.forecast_shape[1])

    @classmethod
    def from_dict(cls, d: dict) -> BCConfig:
        """Build from plain data.

        Args:
            d (dict): the fields.

        Returns:
            The config.

        Raises:
            ValueError: an unknown key or an invalid value.
        """
        # Checkpoints written while this config named the head: "mse" is this policy's (a mixture
        # head's config is the push experiment's, benchmarks/push/gmm_head.py).
        if d.get("action_head") == "mse":
            d = {k: v for k, v in d.items() if k not in ("action_head", "gmm_components")}
        reject_unknown_keys(cls, d, "BC policy config")
        return cls(**d)


@dataclass
class EncoderChoice:
    """The encoder a `BCPolicy` gives each modality kind (`mmf_rl.models.encoders`); images get a
    narrower ConvNet than the forecaster's by default: the policy trains on every frame of the
    recording, not on forecasting windows.

    Args:
        image (str, optional): the image modalities' encoder. Defaults to ``"conv"``.
        image_channels (tuple[int, ...], optional): its ConvNet channels. Defaults to
            ``(16, 32, 32, 32)``.
        vector (str, optional): the vector and sequence modalities' encoder. Defaults to ``"mlp"``.
        vector_kwargs (dict, optional): its keyword arguments.
    """

    image: str = "conv"
    image_channels: tuple[int, ...] = (16, 32, 32, 32)
    vector: str = "mlp"
    vector_kwargs: dict = field(default_factory=dict)

    def spec(self, spec: ModalitySpec) -> ModalitySpec:
        """``spec`` with this choice's encoder for its kind.

        Args:
            spec (ModalitySpec): a modality of the data.

        Returns:
            A copy with ``encoder`` and ``encoder_kwargs`` replaced.
        """
        if spec.kind == "image":
            return replace(spec, encoder=self.image, encoder_kwargs={"channels": tuple(self.image_channels)})
        return replace(spec, encoder=self.vector, encoder_kwargs=dict(self.vector_kwargs))


class BCNetwork(nn.Module):
    """The policy's network on plain tensors, in `BCPolicy.in_keys` order; any leading batch shape.
    Returns the action ``[*B, A]``, or with ``action_chunk`` k > 1 the chunk ``[*B, k, A]``: what
    `head_output` makes of the MLP head's ``outputs_per_step`` numbers per action step (default: the
    action dims)."""

    def __init__(
        self, config: BCConfig, stats: Mapping[str, torch.Tensor], outputs_per_step: int | None = None
    ):
        super().__init__()
        self.config = config
        self.encoders = nn.ModuleDict(
            {s.name: build_encoder(s, config.history, config.d_model) for s in config.modalities}
        )
        self._register_stats(GOAL, "goal", stats)
        if config.privileged_object:
            self._register_stats(OBJECT_POSITION, "object", stats)
        inputs = len(config.modalities) * (config.d_model + 1) + config.goal_dim
        read = config.forecast_read_shape
        inputs += 2 * read[0] * read[1] if read else 0
        inputs += config.latched_forecast is not None  # the age
        inputs += OBJECT_PLANAR_DIMS if config.privileged_object else 0
        self.head = MLP(
            in_features=inputs,
            out_features=(outputs_per_step or config.action_dim) * config.action_chunk,
            num_cells=[config.hidden] * config.depth,
            activation_class=nn.ReLU,
        )

    def _register_stats(self, name: str, buffer: str, stats: Mapping[str, torch.Tensor]) -> None:
        """Buffers ``<buffer>_mean`` and ``<buffer>_std``: the statistics of the input ``name``."""
        names = [f"{name}/mean", f"{name}/std"]
        fix = "use the statistics of the demonstrations (Demonstrations.normalizer.stats)"
        require_stats("BCNetwork", stats, names, fix)
        for stat in ("mean", "std"):
            self.register_buffer(f"{buffer}_{stat}", stats[f"{name}/{stat}"].float().clone())

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        config, m = self.config, len(self.config.modalities)
        observations, presence, goal = inputs[:m], inputs[m : 2 * m], inputs[2 * m]
        batch = goal.shape[:-1]
        n = batch.numel()
        features = []
        for spec, values, present in zip(config.modalities, observations, presence, strict=True):
            values = values.reshape(n, *spec.obs_shape(config.history))
            present = present.reshape(n)
            encoder = self.encoders[spec.name]
            (embedding,) = compute_on_rows(
                present,
                lambda rows, values=values, encoder=encoder: (
                    encoder(values if rows is None else values[rows]),
                ),
                (torch.zeros(n, config.d_model, device=goal.device),),
            )
            features += [embedding, present.unsqueeze(1).float()]
        features.append((goal.reshape(n, -1) - self.goal_mean) / self.goal_std)
        if config.forecast_shape is not None:
            steps = config.forecast_read_shape[0]
            forecast = inputs[2 * m + 1 : 2 * m + 3]
            loc, scale = (x.reshape(n, *config.forecast_shape)[:, :steps] for x in forecast)
            features += [loc.reshape(n, -1), scale.reshape(n, -1).clamp_min(1e-6).log()]
        if config.latched_forecast is not None:
            features.append(inputs[2 * m + 3].reshape(n, 1).float().log1p())
        if config.privileged_object:  # the last input
            position = inputs[-1].reshape(n, -1)[:, :OBJECT_PLANAR_DIMS]
            features.append((position - self.object_mean) / self.object_std)
        raw = self.head(torch.cat(features, -1))
        steps = (config.action_chunk,) if config.action_chunk > 1 else ()
        return self.head_output(raw.reshape(*batch, *steps, -1))

    def head_output(self, raw: torch.Tensor) -> torch.Tensor:
        """The network's output from the head's ``[*B, (k,) outputs_per_step]``: the action in the box
        ``[-1, 1]``."""
        return torch.tanh(raw)


class BCPolicy(TensorDictModule):
    """A behaviour-cloning policy: observation (+ forecast) -> ``"action"`` (see the module doc).

    ``in_keys``/``out_keys`` are its network's. With ``action_chunk`` k > 1 the network writes
    ``"action_chunk"`` and the policy's `TemporalEnsemble` (``ensemble``) then writes ``"action"``
    from it and its state (``ensemble.in_keys``/``out_keys``): the policy acts in an env with
    `transforms`; `predictor` is the network alone, for batches of independent frames.

    Args:
        config (BCConfig): what it reads and its sizes.
        stats (Mapping[str, torch.Tensor]): normalisation statistics of its training data
            (`Demonstrations.normalizer.stats`):
            the sensor windows' (``"<m>/mean"``, ``"<m>/std"``, ``"target/..."``, for its
            `HistoryWindow`) and the goal's (``"goal/mean"``, ``"goal/std"``); with
            ``privileged_object``, the object's planar position's (``"object_position/..."``).
        network (BCNetwork, optional): another action head's network (a subclass's); ``None``: a
            `BCNetwork` writing the action (chunk) itself.
        out_keys (list, optional): the keys ``network`` writes; ``None``: the action (chunk).
        mode (TensorDictModule, optional): the module that writes ``"action"`` (``"action_chunk"``)
            from ``out_keys``; ``None``: none, the network writes it.
    """

    config_class = BCConfig  # what `from_checkpoint` reads the config with

    def __init__(
        self,
        config: BCConfig,
        stats: Mapping[str, torch.Tensor],
        network: BCNetwork | None = None,
        out_keys: list | None = None,
        mode: TensorDictModule | None = None,
    ):
        network = BCNetwork(config, stats) if network is None else network
        in_keys = (
            [(keys.HISTORY, *s.obs_key) for s in config.modalities]
            + [(keys.HISTORY, *s.present_key) for s in config.modalities]
            + [GOAL]
        )
        if config.forecast_shape is not None:
            in_keys += [keys.FORECAST_LOC, keys.FORECAST_SCALE]
        if config.latched_forecast is not None:
            in_keys.append(keys.FORECAST_AGE)
        if config.privileged_object:
            in_keys.append(OBJECT_POSE)
        chunked = config.action_chunk > 1
        super().__init__(network, in_keys=in_keys, out_keys=out_keys or [ACTION_CHUNK if chunked else ACTION])
        self.mode = mode
        self.config = config
        self.stats = {k: v.detach().float().clone() for k, v in stats.items()}
        self.ensemble = (
            TemporalEnsemble(config.action_chunk, config.action_dim, config.chunk_decay) if chunked else None
        )

    def forward(self, tensordict, *args, **kwargs):
        """The network's output; with a ``mode``, then its action (chunk); with action chunks, then
        the ensemble's action (`TemporalEnsemble`)."""
        tensordict = super().forward(tensordict, *args, **kwargs)
        if self.mode is not None:
            tensordict = self.mode(tensordict)
        return tensordict if self.ensemble is None else self.ensemble(tensordict)

    def predictor(self) -> TensorDictModule:
        """The network alone, sharing this policy's weights: writes ``"action"`` (k = 1: the policy
        itself) or the chunk ``"action_chunk"`` of each row of a batch, without the ensemble."""
        if self.ensemble is None:
            return self
        return self._network() if self.mode is None else TensorDictSequential(self._network(), self.mode)

    def _network(self) -> TensorDictModule:
        return TensorDictModule(self.module, in_keys=self.in_keys, out_keys=self.out_keys)

    def loss(self):
        """The loss that trains this policy's head (`train_bc`): torchrl's `BCLoss` (mean squared
        error); for an action-chunk policy `ActionChunkLoss` on the next k actions."""
        return (
            ActionChunkLoss(self.predictor())
            if self.config.action_chunk > 1
            else BCLoss(self, loss_function="mse")
        )

    @classmethod
    def for_demonstrations(
        cls,
        demonstrations: Demonstrations,
        forecasts: ForecastTable | None = None,
        encoders: EncoderChoice | None = None,
        privileged_object: bool = False,
        forecast_steps: int | None = None,
        **sizes,
    ) -> BCPolicy:
        """A policy for the windows, goal and action of ``demonstrations``; it reads forecasts of
        ``forecasts``' shape when given (its first ``forecast_steps``; their age, from a
        `LatchedForecastTable`), and the
        object's position with ``privileged_object``.

        Args:
            demonstrations (Demonstrations): its training samples (modalities, window, goal and action
                dims, normalisation statistics).
            forecasts (ForecastTable, optional): the forecasts it reads (a `LatchedForecastTable`: with
                their age); ``None``: no forecast input.
            encoders (EncoderChoice, optional): the modalities' encoders; ``None``: the defaults.
            privileged_object (bool, optional): also read the object's true position. Defaults to
                ``False``.
            forecast_steps (int, optional): the first steps of each forecast it reads; ``None``: all.
            **sizes: `BCConfig` fields (``d_model``, ``hidden``, ``depth``, ``action_chunk``,
                ``chunk_decay``).

        Returns:
            The policy, untrained.
        """
        if privileged_object:
            demonstrations.check_object_pose("train")
        encoders = encoders or EncoderChoice()
        config = cls.config_class(
            modalities=[encoders.spec(s) for s in demonstrations.specs],
            history=demonstrations.history,
            stride=demonstrations.stride,
            goal_dim=demonstrations.goal_dim,
            action_dim=demonstrations.action_dim,
            forecast_shape=None if forecasts is None else forecasts.shape,
            forecast_steps=forecast_steps,
            latched_forecast=forecasts.rule if isinstance(forecasts, LatchedForecastTable) else None,
            privileged_object=privileged_object,
            **sizes,
        )
        return cls(config, demonstrations.normalizer.stats)

    # -- in an env -------------------------------------------------------------------------------

    def history_window(self) -> HistoryWindow:
        """The env transform writing the ``"history"`` window this policy reads."""
        return HistoryWindow(self.config.modalities, self.stats, self.config.history, self.config.stride)

    def transforms(self, forecast: ForecastTransform | None = None) -> list:
        """The env transforms this policy reads from, in order: its `HistoryWindow`, then the
        forecaster's `ForecastTransform` (``denormalize=False``; a `LatchedForecastTransform` of the
        policy's rule for one trained on latched forecasts) for a policy that reads forecasts; for
        an action-chunk policy, last, an `InitTracker` and its ensemble's state primer.

        Args:
            forecast (ForecastTransform, optional): the forecaster's transform, for a policy that reads
                forecasts.

        Returns:
            The transforms, to put after the env's outages in a `Compose`.

        Raises:
            ValueError: a forecast transform the policy was not trained on (none, one too many, another
                shape, denormalised, or another latch rule).
        """
        return self._readers(forecast) + self._ensemble_transforms()

    def _ensemble_transforms(self) -> list:
        if self.ensemble is None:
            return []
        return [InitTracker(), self.ensemble.make_tensordict_primer()]

    def _readers(self, forecast: ForecastTransform | None) -> list:
        wants = self.config.forecast_shape
        if (forecast is None) != (wants is None):
            raise ValueError(
                "BCPolicy.transforms: "
                + (
                    f"this policy reads forecasts of shape {list(wants)}: pass the ForecastTransform of the "
                    "forecaster it was trained with"
                    if forecast is None
                    else "this policy was trained without forecasts: pass no ForecastTransform"
                )
            )
        if forecast is None:
            return [self.history_window()]
        if forecast.denormalize:
            raise ValueError(
                "BCPolicy.transforms: the policy reads forecasts in the forecaster's normalised frame, as it "
                "was trained; build the transform with ForecastTransform.from_checkpoint(..., "
                "denormalize=False)"
            )
        if (forecast.horizon, forecast.target_dim) != tuple(wants):
            raise ValueError(
                f"BCPolicy.transforms: the policy reads forecasts of shape {list(wants)} (T, D), the "
                f"ForecastTransform writes {[forecast.horizon, forecast.target_dim]}; pass the forecaster "
                "the policy was trained with"
            )
        self._check_latch(forecast)
        return [self.history_window(), forecast]

    def _check_latch(self, forecast: ForecastTransform) -> None:
        """A policy reads the latched forecast (and its age) iff it was trained on one, same rule."""
        rule = self.config.latched_forecast
        if rule is None and isinstance(forecast, LatchedForecastTransform):
            raise ValueError(
                "BCPolicy.transforms: this policy was trained on fresh forecasts, without their age: pass a "
                "ForecastTransform, not a LatchedForecastTransform"
            )
        if rule is not None and getattr(forecast, "rule", None) != rule:
            raise ValueError(
                f"BCPolicy.transforms: this policy reads the latched forecast (rule {rule!r}) and its age, "
                f"as it was trained: pass LatchedForecastTransform.for_trained(model, stats, data_config, "
                f"rule={rule!r}, denormalize=False)"
            )

    # -- checkpoints -----------------------------------------------------------------------------

    def checkpoint_meta(self) -> dict:
        return {"bc_config": self.config.to_dict()}

    def save(self, directory: str | os.PathLike, step: int = 0) -> Path:
        """Write the policy as a checkpoint (safetensors weights and statistics, ``meta.json`` config)
        under ``directory``, atomically.

        Args:
            directory (str | os.PathLike): the checkpoints' directory.
            step (int, optional): the step the checkpoint is named after. Defaults to ``0``.

        Returns:
            The checkpoint's path.
        """
        return save_checkpoint(
            directory, step, self.state_dict(), meta=self.checkpoint_meta(), tensors=self.stats
        )

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> BCPolicy:
        """The policy of a checkpoint.

        Args:
            path (str | os.PathLike): a checkpoint, or a directory's ``last`` one (a run's
                ``checkpoints/``).

        Returns:
            The policy, in eval mode.

        Raises:
            CheckpointError: a checkpoint that is not a behaviour-cloning policy's.
        """
        checkpoint = load_checkpoint(path, with_trainer_state=False)
        if "bc_config" not in checkpoint.meta:
            raise CheckpointError(
                f"{checkpoint.path} is not a behaviour-cloning policy (no 'bc_config' in its meta.json); "
                "pass a checkpoint written by train_bc or BCPolicy.save"
            )
        policy = cls(cls.config_class.from_dict(checkpoint.meta["bc_config"]), checkpoint.tensors)
        load_model_state(policy, checkpoint)
        return policy.eval()


def _drop_label(dropped: Sequence[str]) -> str:
    return "all" if not dropped else "no_" + "_".join(dropped)


@torch.no_grad()
def validation_errors(
    policy: BCPolicy,
    demonstrations: Demonstrations,
    split: str = "val",
    droppable: Sequence[str] = tuple(DEFAULT_DROPOUT),
    forecasts: ForecastTable | LatchedForecastTable | None = None,
    batch_size: int = 256,
) -> dict[str, float]:
    """Mean squared action error on ``split``, with all sensors and with each subset of ``droppable``
    removed from every sample.

    For an action-chunk policy, the error of the chunk's first action (the one it predicts for
    now, as a per-step policy does: the two compare), from its network alone (`BCPolicy.predictor`:
    no ensemble over past chunks, the frames being independent). For a policy with a ``mode``, the
    error of the action it acts with, so any two heads compare.

    Args:
        policy (BCPolicy): the policy (put back in its mode after).
        demonstrations (Demonstrations): the samples.
        split (str, optional): the split scored. Defaults to ``"val"``.
        droppable (Sequence[str], optional): the sensors whose subsets are removed. Defaults to
            ``("image", "force")``.
        forecasts (ForecastTable | LatchedForecastTable, optional): the forecasts under each outage,
            for a policy that reads them.
        batch_size (int, optional): samples per batch. Defaults to ``256``.

    Returns:
        ``mse_all``, ``mse_no_<m>...`` per subset, and ``loss``, their mean.

    Raises:
        ValueError: the split has no demonstration frame.
    """
    if not len(demonstrations.split_frames[split]):
        raise ValueError(f"validation_errors: the {split!r} split has no demonstration frame")
    was_training = policy.training
    policy.eval()
    predictor, chunked = policy.predictor(), policy.config.action_chunk > 1
    errors = {}
    for dropped in drop_sets(droppable):
        loader = DemonstrationLoader(
            demonstrations, split, batch_size, absent=dropped, forecasts=forecasts, shuffle=False
        )
        total, count = 0.0, 0
        for batch in loader:
            predicted = predictor(batch.exclude(ACTION)).get(ACTION_CHUNK if chunked else ACTION)
            predicted = predicted[:, 0] if chunked else predicted
            total += float(((predicted - batch.get(ACTION)) ** 2).sum())
            count += batch.get(ACTION).numel()
        errors[f"mse_{_drop_label(dropped)}"] = total / count
    errors["loss"] = sum(errors.values()) / len(errors)
    policy.train(was_training)
    return errors


def _check_training_inputs(
    policy: BCPolicy,
    demonstrations: Demonstrations,
    removed: Sequence[str],
    forecasts: ForecastTable | LatchedForecastTable | None,
) -> None:
    """Raise unless the demonstrations and ``forecasts`` hold what ``policy`` reads with the ``removed``
    sensors out (validation removes each subset of them)."""
    if (forecasts is None) != (policy.config.forecast_shape is None):
        raise ValueError(
            "train_bc: "
            + (
                "the policy reads forecasts: pass the ForecastTable of its forecaster"
                if forecasts is None
                else "the policy was built without a forecast input: pass no ForecastTable"
            )
        )
    if policy.config.privileged_object:
        for split in ("train", "val"):
            demonstrations.check_object_pose(split)
    latched = forecasts.rule if isinstance(forecasts, LatchedForecastTable) else None
    if forecasts is not None and latched != policy.config.latched_forecast:
        raise ValueError(
            f"train_bc: the policy reads latched forecasts of rule {policy.config.latched_forecast} (None: "
            f"fresh ones), the table serves rule {latched}; build the policy with "
            "BCPolicy.for_demonstrations(demonstrations, forecasts)"
        )
    table = forecasts.table if isinstance(forecasts, LatchedForecastTable) else forecasts
    if table is not None and len(table.loc) < len(demonstrations.goal):
        raise ValueError(
            f"train_bc: the ForecastTable covers {len(table.loc)} frames, the demonstrations hold "
            f"{len(demonstrations.goal)} (episodes added after it was computed); add theirs with "
            "ForecastTable.extended(demonstrations, forecaster, stats)"
        )
    if forecasts is not None and set(removed) - set(forecasts.droppable):
        raise ValueError(
            f"train_bc: training removes {sorted(removed)} (dropout, or the drawn outages) but the "
            f"forecasts cover outages of {list(forecasts.droppable)} only; compute the ForecastTable with "
            f"droppable={sorted(removed)}"
        )


def _check_outages(policy: BCPolicy, outages: OutageSampler | None, dropout: Mapping[str, float]) -> None:
    """Raise unless ``outages`` replace ``dropout`` and were drawn for what ``policy`` reads."""
    if outages is None:
        return
    if dropout:
        raise ValueError(
            f"train_bc: drawn outages replace the dropout, found dropout={dict(dropout)}; pass "
            "dropout={} with them"
        )
    outages.check_reads(policy)


def _outages_meta(dropout: Mapping[str, float], outages: OutageSampler | None) -> dict:
    """What the checkpoint records of the training outages."""
    if outages is None:
        return {"dropout": dict(dropout)}
    return {"dropout": {}, **outages.checkpoint_meta()}


def train_bc(
    policy: BCPolicy,
    demonstrations: Demonstrations,
    config: TrainerConfig,
    *,
    dropout: Mapping[str, float] = DEFAULT_DROPOUT,
    forecasts: ForecastTable | LatchedForecastTable | None = None,
    outages: OutageSampler | None = None,
    run_dir: str | os.PathLike | None = None,
    logger=None,
    resume: bool = False,
) -> dict[str, float]:
    """Clone the demonstrations' actions into ``policy`` (by its `BCPolicy.loss`) with the
    project's `Trainer`: ``config`` sets steps, batch size, optimiser, schedule, seed (the batch
    order and the dropout draws), evaluation and checkpoints (under ``run_dir/checkpoints``;
    ``resume`` continues the last one). ``dropout`` removes sensors per sample (see
    `DemonstrationLoader`); ``forecasts`` must cover those outages when the policy reads
    forecasts. ``outages`` (with ``dropout={}``): each sample's outage is drawn by this
    `OutageSampler` instead, made for what the policy reads; validation still removes each subset
    of the sensors it drops, with ``forecasts``.

    Args:
        policy (BCPolicy): the policy, trained in place.
        demonstrations (Demonstrations): the recording's samples.
        config (TrainerConfig): steps, batch size, optimiser, schedule, seed, evaluation, checkpoints.

    Keyword Args:
        dropout (Mapping[str, float], optional): ``{modality: p}`` removed per sample. Defaults to
            ``DEFAULT_DROPOUT`` (image and force at 0.3).
        forecasts (ForecastTable | LatchedForecastTable, optional): the forecasts under each outage,
            for a policy that reads them.
        outages (OutageSampler, optional): drawn outages instead of ``dropout``.
        run_dir (str | os.PathLike, optional): where ``checkpoints/`` go; ``None``: none.
        logger (torchrl.record.loggers.Logger, optional): where to log.
        resume (bool, optional): continue the last checkpoint under ``run_dir``. Defaults to ``False``.

    Returns:
        The last validation errors (`validation_errors`, ``val/`` prefix); ``{}`` without a
        validation split.

    Raises:
        ValueError: forecasts that do not fit the policy (missing or unread, of another latch rule, or
            not covering the frames or the removed sensors), an outage sampler with ``dropout`` or made
            for another window or forecast than the policy reads, or ``resume`` without
            ``run_dir``.
    """
    _check_outages(policy, outages, dropout)
    removed = list(dropout) if outages is None else list(outages.droppable)
    _check_training_inputs(policy, demonstrations, removed, forecasts)
    chunk = policy.config.action_chunk
    loader = DemonstrationLoader(
        demonstrations,
        "train",
        config.batch_size,
        dropout=dropout,
        forecasts=forecasts,
        outages=outages,
        action_chunk=chunk,
        seed=config.seed,
    )
    with warnings.catch_warnings():
        # torchrl 0.13 warns that a loss without a target network declares none.
        warnings.filterwarnings("ignore", message="The name target_actor_network_params")
        loss = policy.loss()

    def evaluate(model: BCPolicy) -> dict[str, float]:
        errors = validation_errors(model, demonstrations, "val", removed, forecasts)
        return {f"val/{k}": v for k, v in errors.items()}

    trainer = Trainer(
        policy,
        loss,
        loader,
        config,
        run_dir=run_dir,
        logger=logger,
        evaluate=evaluate if len(demonstrations.split_frames["val"]) else None,
        checkpoint_meta={**policy.checkpoint_meta(), **_outages_meta(dropout, outages)},
        checkpoint_tensors=policy.stats,
    )
    if resume:
        if run_dir is None:
            raise ValueError("train_bc: resume=True needs the run_dir to resume from")
        trainer.resume(Path(run_dir) / "checkpoints")
    return trainer.train()
