"""Recorded demonstrations for behaviour cloning: every frame as (history window, goal, action).

`Demonstrations` reads the frames of the project's window cache (`WindowDataset`: decoded,
resized, with per-frame presence) and the goal and action columns of the LeRobot recording
(``mmf-rl record`` writes the scripted pusher's command under ``action``). Unlike forecasting
windows, every frame of an episode is a sample, its first frames too: the history window of
frame ``t`` holds frames ``t - (H-1)·s .. t`` with the episode's first frame repeated where they
would precede it, which is exactly the window `HistoryWindow` writes in an env after a reset. A
policy cloned from these windows therefore sees in closed loop the windows it was trained on.
The object's pose column is read too, for a diagnostic policy told where the object is (a `BCConfig`
option); a batch carries it under the key the env emits it with.
`Demonstrations.with_episodes` adds episodes played in the env (DAgger's labelled states,
`benchmarks/push/dagger.py`) to the training split.

`ForecastTable` holds a trained forecaster's forecast of every demonstration frame, once per
set of modalities a training outage may remove (:func:`drop_sets`), computed from the same
windows `ForecastTransform` would build, so a policy that reads forecasts is trained on the
forecasts it gets under the same outage in closed loop (`ForecastTable.extended`: the same for
added episodes).

`DemonstrationLoader` serves batches with the `WindowLoader` protocol (one epoch per iteration,
deterministic given ``set_epoch``) for `mmf_rl.trainers.Trainer`, with seeded per-sample
modality dropout (or each sample's outage drawn by an `OutageSampler`), and for an action-chunk
policy the demonstrator's next k actions of each frame's episode (`Demonstrations.action_chunks`).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
from tensordict import NestedKey, TensorDict, TensorDictBase
from torch import nn

from mmf_rl import keys
from mmf_rl.datasets import Normalizer, WindowDataset
from mmf_rl.datasets.config import SPLIT_NAMES
from mmf_rl.datasets.lerobot_source import LeRobotSource, load_frame_columns
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.rows import compute_on_rows
from mmf_rl.record import ACTION_KEY, GOAL_KEY, OBJECT_POSE_KEY
from mmf_rl.rl.transforms import trained_per_step_presence

ACTION = "action"  # torchrl's action key: what a policy writes and `BCLoss` reads
# An action-chunk policy's targets (`Demonstrations.action_chunks`): the demonstrator's next k
# actions from a frame, ``[B, k, A]``, and whether each is in the frame's episode, ``[B, k]``.
DEMONSTRATED_CHUNK = "demonstrated_chunk"
DEMONSTRATED_CHUNK_MASK = "demonstrated_chunk_mask"
# The object's planar position is the first numbers (x, y) of its pose
# (`mmf_rl.envs.push.OBJECT_POSE_NAMES`); its normalisation statistics are named with this prefix.
OBJECT_PLANAR_DIMS = 2
OBJECT_POSITION = "object_position"


def _episode_starts(episode: torch.Tensor, first_row: int) -> torch.Tensor:
    """The row of each frame's episode start, for frames numbered from ``first_row`` that follow
    their episodes in order (an episode starts where its index changes)."""
    starts = torch.ones(len(episode), dtype=torch.bool)
    starts[1:] = episode[1:] != episode[:-1]
    rows = torch.arange(first_row, first_row + len(episode))
    return torch.cummax(torch.where(starts, rows, first_row), 0).values


def drop_sets(droppable: Sequence[str]) -> list[tuple[str, ...]]:
    """Every subset of ``droppable``; subset ``i`` holds the modalities whose bit is set in ``i``
    (bit ``j`` for ``droppable[j]``), so a batch's absent flags index it directly.

    Args:
        droppable (Sequence[str]): the modalities that can be removed.

    Returns:
        The ``2 ** len(droppable)`` subsets, as tuples.

    Examples:
        >>> from mmf_rl.rl import drop_sets
        >>> drop_sets(["image", "force"])
        [(), ('image',), ('force',), ('image', 'force')]
    """
    return [tuple(m for j, m in enumerate(droppable) if i >> j & 1) for i in range(2 ** len(droppable))]


class Demonstrations:
    """The frames of a recording as behaviour-cloning samples.

    Args:
        data (WindowDataset): the recording's window cache (of the data config the policy and the
            forecaster read: modalities, history, stride, image size, split).
        goal_feature (str, optional): the vector feature read as the goal the policy is given.
            Defaults to the recorder's ``observation.goal``.
        action_feature (str, optional): the vector feature read as the action it imitates. Defaults
            to ``action``.
        object_feature (str, optional): the object's pose (privileged state, `OBJECT_POSE` in a
            batch); ``None`` for a recording without it. Defaults to the recorder's
            ``observation.object_pose``.

    Attributes: ``specs``, ``history``, ``stride`` (the data config's), ``normalizer`` (the
    training split's statistics, with ``goal/mean``, ``goal/std`` and those of the object's planar
    position, ``object_position/...``, added), ``split_frames`` (cache rows of the samples of each
    split: frames with a finite goal and action), ``object_pose`` (``None`` without one).
    """

    def __init__(
        self,
        data: WindowDataset,
        goal_feature: str = GOAL_KEY,
        action_feature: str = ACTION_KEY,
        object_feature: str | None = OBJECT_POSE_KEY,
    ):
        config = data.config
        self.specs: list[ModalitySpec] = list(data.specs)
        self.history, self.stride = config.history, config.stride
        frames = TensorDict.load_memmap(data.cache_path / "frames")
        self._obs = {s.name: frames.get(s.obs_key).as_subclass(torch.Tensor) for s in self.specs}
        self._present = {s.name: frames.get(s.present_key).as_subclass(torch.Tensor) for s in self.specs}
        episode = frames.get("episode").as_subclass(torch.Tensor)
        source = LeRobotSource(config)
        features = [goal_feature, action_feature] + ([object_feature] if object_feature else [])
        columns = self._columns(source, features, episode)
        self.goal = columns[goal_feature]
        self.action = columns[action_feature]
        self.object_pose = columns[object_feature] if object_feature else None
        rows = torch.arange(len(episode))
        self._episode_start = _episode_starts(episode, first_row=0)
        usable = torch.isfinite(self.goal).all(1) & torch.isfinite(self.action).all(1)
        self.split_frames = {
            name: rows[
                usable & torch.isin(episode, torch.tensor(data.split_episodes[name], dtype=torch.long))
            ]
            for name in SPLIT_NAMES
        }
        stats = {**data.normalizer.stats}
        named = {GOAL: self.goal} | ({} if self.object_pose is None else {OBJECT_POSITION: self.planar()})
        for name, values in named.items():
            train = values[self.split_frames["train"]].double()
            stats[f"{name}/mean"] = train.mean(0).float()
            stats[f"{name}/std"] = train.std(0, correction=0).clamp_min(config.std_floor).float()
        self.normalizer = Normalizer(stats)
        self.goal_dim, self.action_dim = self.goal.shape[1], self.action.shape[1]

    @staticmethod
    def _columns(
        source: LeRobotSource, features: list[str], episode: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """The vector ``features`` per cache row, checked to line up with the cache's frames."""
        for feature in features:
            found = source.features.get(feature)
            if found is None or len(found["shape"]) != 1 or found["dtype"] in ("video", "image", "string"):
                vectors = sorted(
                    name
                    for name, f in source.features.items()
                    if len(f["shape"]) == 1 and f["dtype"] != "string"
                )
                raise ValueError(
                    f"demonstrations: {source.root} has no vector feature {feature!r} "
                    f"(meta/info.json: {found and {'dtype': found['dtype'], 'shape': found['shape']}}); "
                    f"choose one of {vectors}"
                )
        data, _, _ = load_frame_columns(source.meta, [*features, "episode_index"], source.episodes)
        if not np.array_equal(np.asarray(data["episode_index"], dtype=np.int64), episode.numpy()):
            raise ValueError(
                f"demonstrations: the window cache of {source.root} does not line up with its frames "
                "(episode_index differs); the dataset changed after the cache was built: open the "
                "WindowDataset again to rebuild it"
            )
        n = len(episode)
        return {f: torch.from_numpy(np.asarray(data[f], dtype=np.float32).reshape(n, -1)) for f in features}

    def planar(self) -> torch.Tensor:
        """``[N, 2]``: the object's planar position at every cache row."""
        return self.object_pose[:, :OBJECT_PLANAR_DIMS]

    def check_object_pose(self, split: str) -> None:
        """Raise unless every frame of ``split`` has the object's pose (a privileged policy reads it)."""
        if self.object_pose is None:
            raise ValueError(
                "demonstrations: a policy told the object's pose needs the recording's pose column; "
                f"build Demonstrations with object_feature={OBJECT_POSE_KEY!r}"
            )
        if not bool(self.object_pose[self.split_frames[split]].isfinite().all()):
            raise ValueError(
                f"demonstrations: some {split!r} frames have no object pose (episodes added without "
                f"{OBJECT_POSE!r}: saved by an older DAgger round); delete those episodes to play them again"
            )

    def with_episodes(self, episodes: Sequence[TensorDictBase]) -> Demonstrations:
        """These demonstrations with ``episodes`` added to the training split (DAgger's aggregation).

        Each episode is a TensorDict ``[steps]`` of its frames as the env emits them: each
        modality's ``("obs", m)`` and ``("present", m)``, ``"goal"``, and the ``"action"`` to
        imitate; ``"object_pose"`` when the episode has it (NaN rows when not: a policy told the
        object's pose refuses them, `check_object_pose`). The recording's frames keep their rows
        (a `ForecastTable` of them stays valid: `ForecastTable.extended` adds the new rows) and its
        normalisation statistics stay those of the recording, so a policy's inputs mean the same
        whatever it is trained on.
        """
        if not episodes:
            raise ValueError("Demonstrations.with_episodes: no episode to add")
        for index, frames in enumerate(episodes):
            self._check_episode(index, frames)
        n = len(self.goal)
        lengths = torch.tensor([len(frames) for frames in episodes])
        episode = torch.repeat_interleave(torch.arange(len(episodes)), lengths)
        added = copy.copy(self)

        def joined(key) -> torch.Tensor:
            return torch.cat([frames.get(key) for frames in episodes])

        added._obs = {m: torch.cat([o, joined(keys.obs_key(m))]) for m, o in self._obs.items()}
        added._present = {m: torch.cat([p, joined(keys.present_key(m))]) for m, p in self._present.items()}
        added._episode_start = torch.cat([self._episode_start, _episode_starts(episode, first_row=n)])
        added.goal = torch.cat([self.goal, joined(GOAL)])
        added.action = torch.cat([self.action, joined(ACTION)])
        if self.object_pose is not None:
            added.object_pose = torch.cat([self.object_pose, *map(self._episode_object_pose, episodes)])
        new_rows = torch.arange(n, n + len(episode))
        added.split_frames = {**self.split_frames, "train": torch.cat([self.split_frames["train"], new_rows])}
        return added

    def _episode_object_pose(self, frames: TensorDictBase) -> torch.Tensor:
        if OBJECT_POSE in frames.keys():
            return frames.get(OBJECT_POSE)
        return torch.full((len(frames), self.object_pose.shape[1]), math.nan)

    def _check_episode(self, index: int, frames: TensorDictBase) -> None:
        """An episode `with_episodes` can add: every entry the recording's frames have, same shapes
        and dtypes, finite goal and action."""
        expected = {keys.obs_key(m): o for m, o in self._obs.items()}
        expected |= {keys.present_key(m): p for m, p in self._present.items()}
        expected |= {GOAL: self.goal, ACTION: self.action}
        found = frames.keys(include_nested=True)
        if self.object_pose is not None and OBJECT_POSE in found:
            expected[OBJECT_POSE] = self.object_pose
        for key, values in expected.items():
            given = frames.get(key) if key in found else None
            if given is None or given.shape[1:] != values.shape[1:] or given.dtype != values.dtype:
                raise ValueError(
                    f"Demonstrations.with_episodes: episode {index} has {key!r} "
                    f"{None if given is None else (given.dtype, list(given.shape[1:]))}, the recording "
                    f"{(values.dtype, list(values.shape[1:]))} per frame; add frames as the push env "
                    "emits them (demonstration_frames of benchmarks/push/dagger.py)"
                )
        labels = torch.cat([frames.get(GOAL), frames.get(ACTION)], -1)
        if len(frames) == 0 or not bool(labels.isfinite().all()):
            raise ValueError(
                f"Demonstrations.with_episodes: episode {index} is empty or has a non-finite goal or action"
            )

    def rows(self, frames: torch.Tensor, history: int, stride: int) -> torch.Tensor:
        """``[B, history]`` cache rows of the windows ending at ``frames``, oldest first; steps
        before the episode's first frame repeat it (as `HistoryWindow` fills after a reset)."""
        back = torch.arange(history - 1, -1, -1) * stride
        return torch.maximum(frames[:, None] - back, self._episode_start[frames][:, None])

    def observation(self, name: str, frames: torch.Tensor) -> torch.Tensor:
        """Modality ``name`` at ``frames`` as the env emits it (vectors raw, images resized)."""
        return self._obs[name][frames]

    def env_observation(self, frames: torch.Tensor) -> TensorDict:
        """The recorded ``frames`` as the env emits a step of a batch of envs: ``("obs", m)`` single
        frames and ``("present", m)`` flags, batch ``[B]`` (to replay episodes through env transforms)."""
        observation = TensorDict(batch_size=[len(frames)])
        for spec in self.specs:
            observation.set(spec.obs_key, self._obs[spec.name][frames].clone())
            observation.set(spec.present_key, self._present[spec.name][frames].clone())
        return observation

    def episodes(self, split: str) -> tuple[torch.Tensor, torch.Tensor]:
        """The first cache row and the length of each episode with a frame in ``split``."""
        starts = torch.unique(self._episode_start)
        ends = torch.cat([starts[1:], torch.tensor([len(self._episode_start)])])
        used = torch.isin(starts, self._episode_start[self.split_frames[split]])
        return starts[used], (ends - starts)[used]

    def episode_start(self, frames: torch.Tensor) -> torch.Tensor:
        """The cache row of the first frame of each of ``frames``' episodes."""
        return self._episode_start[frames]

    def action_chunks(self, frames: torch.Tensor, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The demonstrated actions at ``frames`` and the ``chunk - 1`` frames after each:
        ``[B, chunk, A]``, and ``[B, chunk]`` whether each step is in the frame's episode with an
        action. Steps past the episode's end (and frames without a finite action) are masked, and
        hold zeros: nothing is invented for them."""
        rows = frames[:, None] + torch.arange(chunk)
        inside = rows.clamp(max=len(self.action) - 1)
        same_episode = self.episode_start(inside) == self.episode_start(frames)[:, None]
        mask = (rows < len(self.action)) & same_episode
        actions = self.action[inside]
        mask &= torch.isfinite(actions).all(-1)
        return torch.where(mask.unsqueeze(-1), actions, 0.0), mask

    def _window_presence(self, spec: ModalitySpec, step_rows: torch.Tensor) -> torch.Tensor:
        present = self._present[spec.name][step_rows]
        return present.all(1) if spec.kind != "vector" else present

    def presence(self, frames: torch.Tensor) -> dict[str, torch.Tensor]:
        """``{m: bool [B]}``: whether the recording has modality ``m`` in the window ending at ``frames``."""
        rows = self.rows(frames, self.history, self.stride)
        return {
            s.name: self._window_presence(s, rows if s.kind != "vector" else rows[:, -1]) for s in self.specs
        }

    def window(
        self,
        frames: torch.Tensor,
        absent: Mapping[str, torch.Tensor] | None = None,
        *,
        specs: Sequence[ModalitySpec] | None = None,
        history: int | None = None,
        stride: int | None = None,
        normalizer: Normalizer | None = None,
        per_step_presence: bool = False,
    ) -> TensorDict:
        """The model window (``("obs", m)``, ``("present", m)``, batch ``[B]``) ending at ``frames``.

        Built by `HistoryWindow`'s rules: vectors normalised, a ``"sequence"``/``"image"``
        modality present only if present at every step (``"vector"``: the last), absent vector
        windows zeroed; with ``per_step_presence`` (a forecaster trained with
        ``data.partial_windows``) present if present at one step at least, its absent steps zeroed
        and marked in ``("present_steps", m)``. ``absent[m]`` (``bool [B]``) removes ``m`` from
        those samples (every step), as a training outage does. ``specs``/``history``/``stride``/
        ``normalizer`` default to the recording's (a forecaster passes its own).
        """
        specs = self.specs if specs is None else specs
        history = self.history if history is None else history
        stride = self.stride if stride is None else stride
        normalizer = self.normalizer if normalizer is None else normalizer
        rows = self.rows(frames, history, stride)
        window = TensorDict(batch_size=[len(frames)])
        for spec in specs:
            self._check_cached(spec)
            step_rows = rows if spec.kind != "vector" else rows[:, -1]
            step_present = self._present[spec.name][step_rows]
            present = step_present
            if spec.kind != "vector":
                present = step_present.any(1) if per_step_presence else step_present.all(1)
            if absent is not None and spec.name in absent:
                present = present & ~absent[spec.name]
            values = self._obs[spec.name][step_rows]
            if per_step_presence and spec.kind != "vector":
                steps = step_present & present.unsqueeze(1)
                values = keys.zero_absent_steps(values, steps)
                window.set(keys.present_steps_key(spec.name), steps)
            if spec.kind != "image":
                values = normalizer.normalize(spec.name, values) * present.view(-1, *[1] * (values.dim() - 1))
            window.set(spec.obs_key, values)
            window.set(spec.present_key, present)
        return window

    def _check_cached(self, spec: ModalitySpec) -> None:
        """Raise unless the recording's cache holds ``spec``'s modality with its shape."""
        if spec.name not in self._obs or tuple(self._obs[spec.name].shape[1:]) != spec.shape:
            cached = {n: list(o.shape[1:]) for n, o in self._obs.items()}
            raise ValueError(
                f"demonstrations: the model reads {spec.name!r} ({spec.kind} {list(spec.shape)}) but the "
                f"recording's cache holds {cached}; build the demonstrations with the data config the "
                "model was trained on"
            )

    def batch(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor] | None = None, action_chunk: int = 1
    ) -> TensorDict:
        """A behaviour-cloning batch: ``"history"`` (the policy's window, `HistoryWindow`'s key),
        ``"goal"`` and ``"object_pose"`` (as the env emits them; the pose when the recording has
        it) and ``"action"`` (the demonstrated command); with ``action_chunk`` k > 1, the next k
        demonstrated actions and their mask too (`action_chunks`)."""
        batch = TensorDict(
            {
                keys.HISTORY: self.window(frames, absent),
                GOAL: self.goal[frames],
                ACTION: self.action[frames],
            },
            batch_size=[len(frames)],
        )
        if self.object_pose is not None:
            batch.set(OBJECT_POSE, self.object_pose[frames])
        if action_chunk > 1:
            actions, mask = self.action_chunks(frames, action_chunk)
            batch.update({DEMONSTRATED_CHUNK: actions, DEMONSTRATED_CHUNK_MASK: mask})
        return batch


@dataclass
class ForecastTable:
    """A forecaster's forecast of every demonstration frame under each outage of ``droppable``.

    ``loc``, ``scale``: ``float32 [N, 2**len(droppable), T, D]`` (``N`` cache rows; NaN for
    frames not computed), in the forecaster's normalised frame (what `ForecastTransform` writes
    with ``denormalize=False``); entry ``[f, i]`` was forecast with the modalities of
    ``drop_sets(droppable)[i]`` removed. ``per_step_presence``: the windows' presence rule
    (`Demonstrations.window`), the forecaster's training one (`for_trained`). A removal covers
    every step of the window: with per-step presence, the forecasts a `ForecastTransform` makes
    in the first H-1 steps of an env outage (a sensor that died mid-window, still present at its
    earlier steps) have no entry here. Built by `compute` or `for_trained`.

    Args:
        loc (torch.Tensor): the forecasts' means, ``float32 [N, 2**len(droppable), T, D]``.
        scale (torch.Tensor): their standard deviations, same shape.
        droppable (tuple[str, ...]): the modalities whose subsets index the second dim.
        per_step_presence (bool, optional): the windows' presence rule. Defaults to ``False``.
    """

    loc: torch.Tensor
    scale: torch.Tensor
    droppable: tuple[str, ...]
    per_step_presence: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        """``(T, D)`` of one forecast."""
        return tuple(self.loc.shape[-2:])

    def lookup(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor]
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``loc``, ``scale`` ``[B, T, D]`` of ``frames`` with the ``absent`` modalities removed."""
        extra = sorted(m for m, a in absent.items() if m not in self.droppable and bool(a.any()))
        if extra:
            raise ValueError(
                f"ForecastTable: no forecasts without {extra}; it was computed for outages of "
                f"{list(self.droppable)} (forecast_table(droppable=...))"
            )
        index = torch.zeros(len(frames), dtype=torch.long)
        for j, name in enumerate(self.droppable):
            if name in absent:
                index += absent[name].long() << j
        loc, scale = self.loc[frames, index], self.scale[frames, index]
        if bool(torch.isnan(loc).any()):
            raise ValueError("ForecastTable: some frames have no forecast; compute the table for their split")
        return loc, scale

    def entries(
        self, frames: torch.Tensor, absent: Mapping[str, torch.Tensor], generator: torch.Generator
    ) -> dict[tuple[str, str], torch.Tensor]:
        """What a policy reads of the forecast at ``frames`` (``("forecast", "loc"/"scale")``), as
        `DemonstrationLoader` sets it in a batch (``generator``: for a table that draws)."""
        loc, scale = self.lookup(frames, absent)
        return {keys.FORECAST_LOC: loc, keys.FORECAST_SCALE: scale}

    @classmethod
    @torch.no_grad()
    def compute(
        cls,
        demonstrations: Demonstrations,
        forecaster: nn.Module,
        stats: Mapping[str, torch.Tensor],
        droppable: Sequence[str],
        *,
        stride: int = 1,
        splits: Sequence[str] = ("train", "val"),
        frames: torch.Tensor | None = None,
        batch_size: int = 256,
        per_step_presence: bool = False,
    ) -> ForecastTable:
        """Run ``forecaster`` (eval mode; normalisation ``stats``, window ``stride`` and presence rule
        ``per_step_presence`` of its run: `for_trained` reads them) on the frames of ``splits`` (or
        the cache rows ``frames``), once per subset of ``droppable`` removed. A window left with no
        present modality gets the target's training prior (mean 0, scale 1), as in
        `ForecastTransform`."""
        config = forecaster.config
        if getattr(config, "action_dim", 0):
            raise ValueError(
                "ForecastTable: this model is an action-conditioned world model (action_dim="
                f"{config.action_dim}); it forecasts only under given future actions. Pass a forecaster "
                "trained without `action` in its data config"
            )
        unknown = sorted(set(droppable) - {s.name for s in config.modalities})
        if unknown:
            raise ValueError(
                f"ForecastTable: droppable {unknown} are not modalities of the forecaster "
                f"({[s.name for s in config.modalities]})"
            )
        forecaster.eval()
        normalizer = Normalizer(dict(stats))
        sets = drop_sets(droppable)
        n = len(demonstrations.goal)
        shape = (n, len(sets), config.horizon, config.target_dim)
        loc, scale = torch.full(shape, math.nan), torch.full(shape, math.nan)
        if frames is None:
            frames = torch.cat([demonstrations.split_frames[s] for s in splits])
        for i, dropped in enumerate(sets):
            for chunk in frames.split(batch_size):
                absent = {m: torch.ones(len(chunk), dtype=torch.bool) for m in dropped}
                window = demonstrations.window(
                    chunk,
                    absent,
                    specs=config.modalities,
                    history=config.history,
                    stride=stride,
                    normalizer=normalizer,
                    per_step_presence=per_step_presence,
                )
                valid = torch.stack([window.get(s.present_key) for s in config.modalities]).any(0)
                prior = (
                    torch.zeros(len(chunk), config.horizon, config.target_dim),
                    torch.ones(len(chunk), config.horizon, config.target_dim),
                )

                def predict(rows, window=window):
                    out = forecaster(window if rows is None else window[rows])
                    return out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)

                loc[chunk, i], scale[chunk, i] = compute_on_rows(valid, predict, prior)
        return cls(loc, scale, tuple(droppable), per_step_presence)

    @classmethod
    def for_trained(
        cls,
        demonstrations: Demonstrations,
        model: nn.Module,
        stats: Mapping[str, torch.Tensor],
        data_config: Mapping,
        droppable: Sequence[str],
        *,
        per_step_presence: bool | None = None,
        **options,
    ) -> ForecastTable:
        """`compute` for a trained forecaster (`load_trained_model`'s triple), with the window stride
        and presence rule of its data config, as `ForecastTransform.for_trained` reads them (an
        explicit ``per_step_presence`` overrides the rule, `trained_per_step_presence`);
        ``options``: ``splits``, ``frames``, ``batch_size``."""
        per_step_presence = trained_per_step_presence(data_config, per_step_presence, cls.__name__)
        stride = int(data_config.get("stride", 1))
        return cls.compute(
            demonstrations,
            model,
            stats,
            droppable,
            stride=stride,
            per_step_presence=per_step_presence,
            **options,
        )

    def extended(
        self,
        demonstrations: Demonstrations,
        forecaster: nn.Module,
        stats: Mapping[str, torch.Tensor],
        *,
        stride: int = 1,
        batch_size: int = 256,
    ) -> ForecastTable:
        """This table of ``demonstrations``' first frames, with the forecasts of the frames added
        after them (`Demonstrations.with_episodes`) computed as `compute` computes them (same
        ``forecaster``, ``stats``, ``stride``, outages, presence rule)."""
        n, total = len(self.loc), len(demonstrations.goal)
        if total < n:
            raise ValueError(
                f"ForecastTable.extended: the demonstrations hold {total} frames, fewer than the table's "
                f"{n}; pass the demonstrations the table was computed for, with episodes added"
            )
        added = self.compute(
            demonstrations,
            forecaster,
            stats,
            self.droppable,
            stride=stride,
            frames=torch.arange(n, total),
            batch_size=batch_size,
            per_step_presence=self.per_step_presence,
        )
        return ForecastTable(
            torch.cat([self.loc, added.loc[n:]]),
            torch.cat([self.scale, added.scale[n:]]),
            self.droppable,
            self.per_step_presence,
        )


class OutageSampler(Protocol):
    """Each training sample's outage, drawn in place of `DemonstrationLoader`'s independent
    ``dropout``, with what a policy that reads forecasts is served under it. The push experiment's
    replays of the env's outage processes are one (``benchmarks/push/replayed_outages.py``)."""

    @property
    def droppable(self) -> tuple[str, ...]:
        """The modalities some draw removes (validation removes each subset of them)."""

    def draw(
        self, frames: torch.Tensor, generator: torch.Generator, with_forecasts: bool
    ) -> tuple[dict[str, torch.Tensor], dict[NestedKey, torch.Tensor]]:
        """The modalities each sample of ``frames`` lacks (``{m: bool [B]}``) and, ``with_forecasts``,
        the forecast entries it is served (``{key: [B, ...]}``)."""

    def check_reads(self, policy) -> None:
        """Raise unless the draws were made for what the `BCPolicy` ``policy`` reads (its window, its
        forecast)."""

    def checkpoint_meta(self) -> dict:
        """What a policy's checkpoint records of the outages it was trained on."""


class DemonstrationLoader:
    """Behaviour-cloning batches of one split, with the `WindowLoader` protocol.

    Args:
        demonstrations (Demonstrations): the samples.
        split (str): ``"train"``, ``"val"`` or ``"test"``.
        batch_size (int): samples per batch.

    Keyword Args:
        dropout (Mapping[str, float], optional): ``{modality: p}``: each sample loses each of these modalities
            with probability ``p``, independently (drawn per epoch from ``seed``; a sample never loses all of
            its modalities: the draws that would are not applied).
        absent (Sequence[str], optional): modalities removed from every sample (an evaluation under a
            fixed outage).
        forecasts (ForecastTable, optional): a `ForecastTable` covering the outages: batches then carry
            ``("forecast", "loc"/"scale")`` of the outage each sample is under (a
            `mmf_rl.rl.latched_forecast.LatchedForecastTable`: the latched forecast and its age).
        outages (OutageSampler, optional): an `OutageSampler` instead of ``dropout``: each sample's
            outage is its draw, with the forecast served there (when ``forecasts`` is given: the
            policy reads forecasts).
        action_chunk (int, optional): k > 1: batches carry the next k demonstrated actions and their mask
            (`Demonstrations.action_chunks`), an action-chunk policy's targets.
        shuffle (bool, optional): shuffle each epoch; ``None`` (default): for ``"train"``.
        seed (int, optional): orders the epochs and draws the dropout (``(seed, epoch)``). Defaults to
            ``0``.
        drop_last (bool, optional): drop the last, smaller batch; ``None`` (default): when shuffled.

    Raises:
        ValueError: an unknown split, ``batch_size`` or ``action_chunk`` below 1, ``dropout``/``absent``
            naming a modality the demonstrations lack or a probability outside ``[0, 1]``, or
            ``outages`` with ``dropout`` or ``absent``.
    """

    def __init__(
        self,
        demonstrations: Demonstrations,
        split: str,
        batch_size: int,
        *,
        dropout: Mapping[str, float] | None = None,
        absent: Sequence[str] = (),
        forecasts: ForecastTable | None = None,
        outages: OutageSampler | None = None,
        action_chunk: int = 1,
        shuffle: bool | None = None,
        seed: int = 0,
        drop_last: bool | None = None,
    ):
        if split not in SPLIT_NAMES:
            raise ValueError(f"unknown split {split!r}; expected one of {list(SPLIT_NAMES)}")
        if batch_size < 1 or action_chunk < 1:
            raise ValueError(f"batch_size and action_chunk must be >= 1, found {batch_size}, {action_chunk}")
        names = [s.name for s in demonstrations.specs]
        dropout = dict(dropout or {})
        unknown = sorted((set(dropout) | set(absent)) - set(names))
        bad = {m: p for m, p in dropout.items() if not 0.0 <= p <= 1.0}
        if unknown or bad:
            raise ValueError(
                f"DemonstrationLoader: dropout {dropout} / absent {list(absent)} must name modalities of "
                f"{names} with probabilities in [0, 1]"
            )
        self.demonstrations, self.split, self.batch_size = demonstrations, split, batch_size
        if outages is not None and (dropout or absent):
            raise ValueError(
                "DemonstrationLoader: drawn outages replace dropout and absent; give one or the other"
            )
        self.dropout, self.absent, self.forecasts = dropout, tuple(absent), forecasts
        self.outages = outages
        self.action_chunk = action_chunk
        self.shuffle = split == "train" if shuffle is None else shuffle
        self.drop_last = self.shuffle if drop_last is None else drop_last
        self.seed, self.epoch = seed, 0

    def set_epoch(self, epoch: int) -> None:
        """Set the epoch the next iteration's order and dropout are drawn for.

        Args:
            epoch (int): the epoch.
        """
        self.epoch = epoch

    def __len__(self) -> int:
        n = len(self.demonstrations.split_frames[self.split])
        return n // self.batch_size if self.drop_last else math.ceil(n / self.batch_size)

    def _absent(self, frames: torch.Tensor, generator: torch.Generator) -> dict[str, torch.Tensor]:
        n = len(frames)
        absent = {m: torch.ones(n, dtype=torch.bool) for m in self.absent}
        # Drawn for every modality of the protocol each batch: the stream does not depend on outcomes.
        draws = {m: torch.rand(n, generator=generator) < p for m, p in sorted(self.dropout.items())}
        if draws:
            none = torch.zeros(n, dtype=torch.bool)
            kept = {
                m: present & ~absent.get(m, none) & ~draws.get(m, none)
                for m, present in self.demonstrations.presence(frames).items()
            }
            nothing_left = ~torch.stack(list(kept.values())).any(0)
            for m, drawn in draws.items():
                absent[m] = absent.get(m, none) | (drawn & ~nothing_left)
        return absent

    def _outages(self, frames: torch.Tensor, generator: torch.Generator) -> tuple[dict, dict]:
        """The modalities each sample lacks and the forecast entries it gets."""
        with_forecasts = self.forecasts is not None
        if self.outages is not None:
            return self.outages.draw(frames, generator, with_forecasts)
        absent = self._absent(frames, generator)
        return absent, self.forecasts.entries(frames, absent, generator) if with_forecasts else {}

    def __iter__(self) -> Iterator[TensorDict]:
        frames = self.demonstrations.split_frames[self.split]
        generator = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
        if self.shuffle:
            frames = frames[torch.randperm(len(frames), generator=generator)]
        stop = len(frames) // self.batch_size * self.batch_size if self.drop_last else len(frames)
        for first in range(0, stop, self.batch_size):
            chunk = frames[first : first + self.batch_size]
            absent, served = self._outages(chunk, generator)
            batch = self.demonstrations.batch(chunk, absent, self.action_chunk)
            for key, value in served.items():
                batch.set(key, value)
            yield batch
        self.epoch += 1
