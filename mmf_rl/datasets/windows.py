"""Forecasting windows served from the cache as batches of the TensorDict contract."""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterator
from pathlib import Path

import torch
from tensordict import MemoryMappedTensor, TensorDict

from mmf_rl.datasets.augment import TrainingAugmentation
from mmf_rl.datasets.cache import CACHE_META, action_offsets, open_cache, window_offsets
from mmf_rl.datasets.config import OBSERVED, SPLIT_NAMES, DataConfig
from mmf_rl.datasets.lerobot_source import LeRobotSource
from mmf_rl.datasets.planar import check_pairs, rotate_frames, rotate_pairs
from mmf_rl.datasets.protocols import outage_statistics, replay_outages, training_dropout
from mmf_rl.datasets.splits import Normalizer, episode_splits, mean_std
from mmf_rl.keys import (
    FUTURE_ACTION,
    TARGET,
    TARGET_PAST,
    ModalitySpec,
    present_steps_key,
    zero_absent_steps,
)

logger = logging.getLogger(__name__)

# A modality absent on more of the frames than this is an error unless its config sets `allow_absent`.
MAX_ABSENT_FRACTION = 0.5
# Image bytes gathered through one mapping of the cache's image columns before they are mapped
# afresh (`WindowDataset._map_images`): what bounds the pages a reader keeps resident. Image
# tables no larger than this stay mapped once.
REMAP_IMAGE_BYTES = 64 * 2**20
# A modality's missing or undecodable files a warning or error names; it then says how many more.
SHOWN_FILES = 3


def _first_files(problems: list[str], root: Path) -> str:
    """``N file(s): A, B, C and M more``: the first SHOWN_FILES of a modality's problem files."""
    shown = ", ".join(p.removeprefix(f"{root}/") for p in problems[:SHOWN_FILES])
    more = f" and {len(problems) - SHOWN_FILES} more" if len(problems) > SHOWN_FILES else ""
    return f"{len(problems)} file(s): {shown}{more}"


def _plain(tensor: torch.Tensor) -> torch.Tensor:
    """The memory-mapped tensor as a plain ``torch.Tensor`` view (no subclass dispatch per gather)."""
    return tensor.as_subclass(torch.Tensor)


def _wide_rows(frames: torch.Tensor) -> torch.Tensor:
    """``uint8 [N, *shape]`` frames viewed as ``[N, row_bytes / 8]`` int64 when the size allows.

    Gathering rows copies element by element; 8-byte elements make an image gather several
    times faster than 1-byte ones. The result is viewed back as uint8 after the gather.
    """
    row_bytes = frames[0].numel() * frames.element_size()
    if row_bytes % 8:
        return frames
    return frames.reshape(len(frames), row_bytes).view(torch.int64)


class WindowDataset:
    """A LeRobot dataset as forecasting windows, with splits, normalisation and presence.

    Opening builds the window cache if no valid one matches the dataset files and the config,
    otherwise memory-maps the existing one (``built`` tells which). Batches are gathered with
    one vectorised index per key: ``frames[start[:, None] + offsets]``.

    Attributes: ``specs`` (one :class:`ModalitySpec` per modality, for the model),
    ``target_dim``, ``action_shape`` (``(S, A)`` of ``"future_action"`` when the config sets
    ``action``, else ``None``), ``split_episodes`` and ``split_windows`` (window ids per split),
    ``normalizer`` (training-split statistics; ``normalizer.stats`` is the plain dict to store),
    ``observed_outages`` (per modality, its outages in the training episodes: ``fraction`` of frames
    absent, ``outages``, ``mean_burst``, ``max_burst``; ``missing: observed`` replays them),
    ``report`` (what was missing or skipped), ``cache_path``.

    Args:
        config (DataConfig): the dataset, its modalities and target, the window geometry, the split and
            the training missingness protocol.
        num_workers (int, optional): the decode processes of a cache build; ``None`` (default): one per
            core when there are enough frames to repay their start-up, ``0``: none. They are spawned, so
            a script that builds a cache must guard its entry point with
            ``if __name__ == "__main__":``.

    Raises:
        FileNotFoundError: a ``required`` modality's files are missing or undecodable.
        ValueError: a modality absent on more than half of the frames (unless ``allow_absent``), no
            valid frame for a normalisation statistic, or ``planar``/``top_down``/``raw_dims`` that do
            not fit the features; the message names the key and the fix.

    Examples:
        A tiny LeRobot recording of two vector features, written on the spot:

        >>> import tempfile
        >>> from pathlib import Path
        >>> import numpy as np
        >>> from lerobot.datasets.lerobot_dataset import LeRobotDataset
        >>> from mmf_rl.datasets import DataConfig, WindowDataset
        >>> tmp = Path(tempfile.mkdtemp())
        >>> vector = {"dtype": "float32", "shape": (3,), "names": None}
        >>> recording = LeRobotDataset.create(
        ...     repo_id="local/tiny", fps=10, root=tmp / "tiny", use_videos=False,
        ...     features={"observation.state": vector, "observation.force": vector},
        ... )
        >>> for episode in range(5):
        ...     for frame in range(12):
        ...         recording.add_frame({
        ...             "observation.state": np.full(3, frame, dtype=np.float32),
        ...             "observation.force": np.random.randn(3).astype(np.float32),
        ...             "task": "push",
        ...         })
        ...     recording.save_episode()
        >>> recording.finalize()

        Its windows: 4 observed steps, 3 forecast, so 6 windows per 12-frame episode:

        >>> config = DataConfig.from_dict({
        ...     "root": str(tmp / "tiny"),
        ...     "modalities": {"state": "observation.state", "force": "observation.force"},
        ...     "target": {"feature": "observation.state", "dims": [0, 1]},
        ...     "history": 4,
        ...     "horizon": 3,
        ...     "split_fractions": [0.6, 0.2, 0.2],
        ...     "cache_dir": str(tmp / "cache"),
        ... })
        >>> data = WindowDataset(config, num_workers=0)
        >>> [(spec.name, spec.kind, spec.shape) for spec in data.specs], data.target_dim
        ([('force', 'sequence', (3,)), ('state', 'sequence', (3,))], 2)
        >>> {split: len(windows) for split, windows in data.split_windows.items()}
        {'train': 18, 'val': 6, 'test': 6}
        >>> batch = next(iter(data.loader("train", batch_size=8)))
        >>> batch["obs", "force"].shape, batch["present", "force"].shape, batch["target"].shape
        (torch.Size([8, 4, 3]), torch.Size([8]), torch.Size([8, 3, 2]))
        >>> import shutil
        >>> shutil.rmtree(tmp)
    """

    def __init__(self, config: DataConfig, num_workers: int | None = None):
        self.config = config
        source = LeRobotSource(config)
        self.cache_path, self.report, self.built = open_cache(source, num_workers)
        self.specs: list[ModalitySpec] = source.specs
        self.target_dim: int = source.target_dim
        self.action_shape: tuple[int, int] | None = (
            None if source.action_dim is None else (config.horizon * config.stride, source.action_dim)
        )
        frames = TensorDict.load_memmap(self.cache_path / "frames")
        self._check_presence(source, frames)
        windows = TensorDict.load_memmap(self.cache_path / "windows")
        self._obs = {spec.name: _plain(frames.get(spec.obs_key)) for spec in self.specs}
        # Each image column's file, dtype and shape: what maps it afresh, alone (`_map_images`). Not the
        # mapping itself, which would keep resident every page read through it.
        columns = {spec.name: frames.get(spec.obs_key) for spec in self.specs if spec.kind == "image"}
        self._image_columns = {name: (c.filename, c.dtype, c.shape) for name, c in columns.items()}
        self._map_images()
        self._target = _plain(frames.get("target"))
        # The value each window's target is measured from, at its last observed frame (None: absolute).
        self._anchor = None
        if config.target.relative_to is not None:
            self._anchor = _plain(frames.get("target_reference"))
        elif config.target.relative:
            self._anchor = self._target
        self.frame_episode = _plain(frames.get("episode"))
        self.window_start = _plain(windows.get("start"))
        self.window_episode = _plain(windows.get("episode"))
        self._observed, self._future = window_offsets(config.history, config.horizon, config.stride)
        self.presence = {s.name: _plain(windows.get(s.present_key)) for s in self.specs}
        self._frame_present = self._partial_presence(frames) if config.partial_windows else {}
        self._action = _plain(frames.get("action")) if self.action_shape is not None else None
        self._action_offsets = action_offsets(config.history, config.horizon, config.stride)

        # A required modality means every sample has it: windows where it is absent are left out.
        usable = torch.ones(len(self.window_start), dtype=torch.bool)
        for spec in self.specs:
            if spec.required:
                usable &= self.presence[spec.name]
        self.report["skipped"]["windows_without_required_modality"] = int((~usable).sum())

        self.split_episodes = episode_splits([e[0] for e in self.report["episodes"]], config)
        self.split_windows = {
            name: (usable & torch.isin(self.window_episode, torch.tensor(episodes, dtype=torch.long)))
            .nonzero()
            .flatten()
            for name, episodes in self.split_episodes.items()
        }
        self._check_planar()
        self.normalizer = Normalizer(self._train_stats(frames))
        self.observed_outages = self._observed_outages(frames)
        self.train_presence = self._train_presence()

    def _check_planar(self) -> None:
        """The ``planar`` pairs index their vectors and ``top_down`` marks cameras only."""
        for spec in self.specs:
            modality = self.config.modalities[spec.name]
            if spec.kind == "image" and modality.planar:
                raise ValueError(
                    f"data config: `modalities.{spec.name}.planar` names dims of a camera; a camera that "
                    "maps the ground plane takes `top_down: true` instead"
                )
            if spec.kind != "image" and modality.top_down:
                raise ValueError(
                    f"data config: `modalities.{spec.name}.top_down` is for cameras, and {spec.name!r} is a "
                    f"{spec.kind}; mark its [x, y] dims with `planar` instead"
                )
            raw = modality.raw_dims or []
            check_pairs(modality.planar, spec.shape[0], raw, f"modalities.{spec.name}.planar")
        check_pairs(self.config.target.planar, self.target_dim, [], "target.planar")
        if self.action_shape is not None:
            check_pairs(self.config.action.planar, self.action_shape[1], [], "action.planar")

    def _map_images(self) -> None:
        """Map the cache's image columns afresh (their files only, not the other columns).

        Every page a gather reads stays resident in the mapping it was read through, so one mapping
        kept for a whole run would hold as much of the image table as the run has read: up to all
        of it. `batch` maps them afresh every ``REMAP_IMAGE_BYTES``; the pages dropped with the old
        mapping stay in the page cache, so the next reads of them need no disk access.
        """
        for name, (filename, dtype, shape) in self._image_columns.items():
            self._obs[name] = _wide_rows(_plain(MemoryMappedTensor.from_filename(filename, dtype, shape)))
        self._image_table_bytes = sum(
            self._obs[name].numel() * self._obs[name].element_size() for name in self._image_columns
        )
        self._image_bytes_read = 0

    def _partial_presence(self, frames: TensorDict) -> dict[str, torch.Tensor]:
        """Per-frame presence of the windowed modalities; their window presence becomes "present at
        some step" (``data.partial_windows``)."""
        observed = self.window_start[:, None] + self._observed
        frame_present = {}
        for spec in self.specs:
            if spec.kind != "vector":
                frame_present[spec.name] = _plain(frames.get(spec.present_key))
                self.presence[spec.name] = frame_present[spec.name][observed].any(1)
        return frame_present

    def _check_presence(self, source: LeRobotSource, frames: TensorDict) -> None:
        problems = {}
        for name, paths in self.report["missing_files"].items():
            problems.setdefault(name, []).extend(f"{p} (missing)" for p in paths)
        for name, errors in self.report["undecodable_files"].items():
            problems.setdefault(name, []).extend(f"{p} (undecodable: {e})" for p, e in errors.items())
        if problems:
            # The warning and the error show each modality's first files; `mmf-rl -v` logs them all.
            logger.debug("dataset %s: every missing or undecodable file: %s", source.root, problems)
        required = [n for n in problems if source.modalities[n].spec.required]
        if required:
            summary = self._problem_summary(source, problems, required)
            raise FileNotFoundError(
                f"required modality absent from {source.root}:{summary}\n  Restore the files, or set "
                "`required: false` for it to train with the modality marked absent"
            )
        self._check_mostly_absent(source, frames)
        if problems:
            warnings.warn(
                f"dataset {source.root}: modality absent where these video files or parquet images are "
                "missing or undecodable, marked present=False there:"
                + self._problem_summary(source, problems, list(problems)),
                stacklevel=3,
            )

    def _problem_summary(
        self, source: LeRobotSource, problems: dict[str, list[str]], names: list[str]
    ) -> str:
        """Per modality of ``names``, how many files and the first few (relative to the dataset root);
        then, on a line of its own, where the full list is. A recording with a misplaced video folder
        misses every file, and a message naming each would run to thousands of characters."""
        lines = "; ".join(
            f"{n!r} ({source.modalities[n].feature}): {_first_files(problems[n], source.root)}" for n in names
        )
        return (
            f" {lines}\n  The full list is in {self.cache_path / CACHE_META} (`missing_files`, "
            f"`undecodable_files`) and in the log of `mmf-rl -v`; `mmf-rl inspect {source.root}` also "
            "finds files under a near-miss path (video/ for videos/)"
        )

    def _check_mostly_absent(self, source: LeRobotSource, frames: TensorDict) -> None:
        """A modality absent on more than half of the frames is an error unless its config accepts it
        (``allow_absent``): otherwise the model would silently train without it."""
        for name, m in source.modalities.items():
            present = _plain(frames.get(m.spec.present_key))
            absent = 1.0 - present.float().mean().item() if len(present) else 0.0
            if absent <= MAX_ABSENT_FRACTION or self.config.modalities[name].allow_absent:
                continue
            cause, fix = self._absence_cause(name, source)
            raise ValueError(
                f"modality {name!r} ({m.feature}) is absent on {absent:.1%} of the {len(present)} frames of "
                f"{source.root}: {cause}. The model would train without it. {fix}, or accept it with "
                f"data.modalities.{name}.allow_absent=true"
            )

    def _absence_cause(self, name: str, source: LeRobotSource) -> tuple[str, str]:
        """Why modality ``name`` is absent (from the cache report) and the fix to suggest first."""
        missing = self.report["missing_files"].get(name, [])
        errors = self.report["undecodable_files"].get(name, {})
        if errors:
            path, error = next(iter(errors.items()))
            cause = f"{len(errors)} undecodable file(s), e.g. {path} ({error})"
            if "FrameTimestampError" in error:
                return cause, (
                    "The dataset's `timestamp` column does not match its video frames (`mmf-rl inspect "
                    f"{source.root}` reports the drift from frame_index/fps): set "
                    "data.video_sync=frame_index "
                    "to decode frame k of an episode at k/fps (a larger data.tolerance_s would decode, but "
                    "pair rows with frames as far apart as the drift)"
                )
            return cause, "Restore or re-encode the camera's files"
        if missing:
            return f"{len(missing)} video file(s) missing, e.g. {missing[0]}", "Restore the video files"
        return (
            "non-finite values or its validity feature mark it absent",
            f"Check the feature {source.modalities[name].feature!r} (`mmf-rl inspect {source.root}` lists "
            "its NaN spans and outages)",
        )

    def _train_stats(self, frames: TensorDict) -> dict[str, torch.Tensor]:
        train_frames = torch.isin(
            self.frame_episode, torch.tensor(self.split_episodes["train"], dtype=torch.long)
        )
        stats = {}
        floor = self.config.std_floor
        for spec in self.specs:
            if spec.kind != "image":
                valid = train_frames & _plain(frames.get(spec.present_key))
                mean, std = mean_std(self._obs[spec.name], valid, floor, f"modality {spec.name!r}")
                raw = self.config.modalities[spec.name].raw_dims or []
                if any(not 0 <= i < mean.numel() for i in raw):
                    raise ValueError(
                        f"data config: `modalities.{spec.name}.raw_dims` {raw} must index its "
                        f"{mean.numel()} dims (after `dims`); fix the indices"
                    )
                mean[raw], std[raw] = 0.0, 1.0
                stats[f"{spec.name}/mean"], stats[f"{spec.name}/std"] = mean, std
        if self._anchor is not None:
            future, _ = self._targets(self.window_start[self.split_windows["train"]], with_past=False)
            rows = future.reshape(-1, future.shape[-1])
            valid = torch.ones(rows.shape[0], dtype=torch.bool)
        else:
            rows, valid = self._target, train_frames & _plain(frames.get("target_valid"))
        stats["target/mean"], stats["target/std"] = mean_std(rows, valid, floor, "the target")
        if self._action is not None:
            valid = train_frames & _plain(frames.get("action_valid"))
            stats[f"{FUTURE_ACTION}/mean"], stats[f"{FUTURE_ACTION}/std"] = mean_std(
                self._action, valid, floor, f"the action ({self.config.action.feature!r})"
            )
        return stats

    def _targets(self, start: torch.Tensor, with_past: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Future ``[N, T, D]`` (and past ``[N, H, D]``) target values of the windows at ``start``,
        unnormalised, measured from the anchor at the last observed frame when the config sets one
        (``target.relative``: the target itself; ``target.relative_to``: another feature)."""
        future = self._target[start[:, None] + self._future]
        past = self._target[start[:, None] + self._observed] if with_past else None
        if self._anchor is not None:
            anchor = self._anchor[start + self._observed[-1]][:, None]
            future = future - anchor
            past = past - anchor if past is not None else None
        return future, past

    def _observed_outages(self, frames: TensorDict) -> dict[str, dict[str, float]]:
        """Per modality, the outages of its per-frame presence in the training episodes
        (:func:`outage_statistics`): what ``missing: observed`` replays."""
        train_frames = torch.isin(
            self.frame_episode, torch.tensor(self.split_episodes["train"], dtype=torch.long)
        )
        return {
            spec.name: outage_statistics(
                _plain(frames.get(spec.present_key))[train_frames], self.frame_episode[train_frames]
            )
            for spec in self.specs
        }

    def _train_presence(self) -> dict[str, torch.Tensor]:
        """Window presence with the config's training missingness protocol applied to train windows:
        replayed outages first, then the fractions of windows."""
        config = self.config
        outages = config.replayed_outages
        outages = self.observed_outages if outages == OBSERVED else {k: vars(v) for k, v in outages.items()}
        if not config.window_dropout and not any(0.0 < o["fraction"] < 1.0 for o in outages.values()):
            return self.presence
        train = self.split_windows["train"]
        dropped = {name: mask[train] for name, mask in self.presence.items()}
        if outages:
            start = self.window_start[train]
            rows = {
                spec.name: start[:, None] + (self._observed if spec.kind != "vector" else self._observed[-1:])
                for spec in self.specs
            }
            dropped = replay_outages(dropped, rows, outages, len(self.frame_episode), config.missing_seed)
        if config.window_dropout:
            dropped = training_dropout(dropped, config.window_dropout, config.missing_seed)
        presence = {name: mask.clone() for name, mask in self.presence.items()}
        for name, mask in dropped.items():
            presence[name][train] = mask
        return presence

    def __len__(self) -> int:
        return len(self.window_start)

    def batch(
        self, window_ids: torch.Tensor, split: str = "eval", angles: torch.Tensor | None = None
    ) -> TensorDict:
        """The batch of windows ``window_ids``, following `mmf_rl.keys` (vectors and target normalised).

        Args:
            window_ids (torch.Tensor): ``long [B]`` window indices (e.g. from ``split_windows``).
            split (str, optional): ``"train"`` applies the training missingness protocol; any other
                value reads the data's own presence. Defaults to ``"eval"``.
            angles (torch.Tensor, optional): ``[B]`` radians that turn each window's ground plane: its
                ``planar`` dims and ``top_down`` cameras (:mod:`~mmf_rl.datasets.planar`).

        Returns:
            A TensorDict of batch size ``[B]``.
        """
        presence = self.train_presence if split == "train" else self.presence
        if self._image_table_bytes > REMAP_IMAGE_BYTES and self._image_bytes_read > REMAP_IMAGE_BYTES:
            self._map_images()
        start = self.window_start[window_ids]
        observed = start[:, None] + self._observed
        batch = TensorDict(batch_size=[len(window_ids)])
        for spec in self.specs:
            present = presence[spec.name][window_ids]
            rows = observed if spec.kind != "vector" else observed[:, -1]
            values = self._obs[spec.name][rows]
            modality = self.config.modalities[spec.name]
            if spec.kind == "image":
                values = values.view(torch.uint8).view(*rows.shape, *spec.shape)
                self._image_bytes_read += values.numel()
                if angles is not None and modality.top_down:
                    values = rotate_frames(values, angles)
            else:
                if angles is not None:
                    values = rotate_pairs(values, modality.planar, angles)
                values = self.normalizer.normalize(spec.name, values)
                # Absent samples carry zeros, not the stored placeholder: never NaN, never data.
                values = values * present.view(-1, *[1] * (values.dim() - 1))
            if spec.name in self._frame_present:
                steps = self._frame_present[spec.name][rows] & present[:, None]
                batch.set(present_steps_key(spec.name), steps)
                values = zero_absent_steps(values, steps)
            batch.set(spec.obs_key, values)
            batch.set(spec.present_key, present)
        future, past = self._targets(start, with_past=self.config.include_target_past)
        if angles is not None:
            future = rotate_pairs(future, self.config.target.planar, angles)
            past = rotate_pairs(past, self.config.target.planar, angles) if past is not None else None
        batch.set(TARGET, self.normalizer.normalize("target", future))
        if past is not None:
            batch.set(TARGET_PAST, self.normalizer.normalize("target", past))
        if self._action is not None:
            actions = self._action[start[:, None] + self._action_offsets]
            if angles is not None:
                actions = rotate_pairs(actions, self.config.action.planar, angles)
            batch.set(FUTURE_ACTION, self.normalizer.normalize(FUTURE_ACTION, actions))
        return batch

    def loader(
        self,
        split: str,
        batch_size: int,
        shuffle: bool | None = None,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        drop_last: bool | None = None,
        augment: TrainingAugmentation | None = None,
    ) -> WindowLoader:
        """Batches of ``split`` (see :class:`WindowLoader`).

        Args:
            split (str): ``"train"``, ``"val"`` or ``"test"``.
            batch_size (int): windows per batch.
            shuffle (bool, optional): shuffle (seeded, per epoch); ``None`` (default): for ``"train"``
                only.
            seed (int, optional): the shuffle's seed. Defaults to ``0``.
            rank (int, optional): this process's rank among ``world_size``. Defaults to ``0``.
            world_size (int, optional): processes sharing the split. Defaults to ``1``.
            drop_last (bool, optional): drop the last, smaller batch; ``None``: when shuffling.
            augment (TrainingAugmentation, optional): transforms the image modalities and turns the
                ground plane of every batch (meant for the training split).

        Returns:
            The loader; each iteration over it is one epoch.

        Raises:
            ValueError: ``augment`` turns the ground plane but the config marks nothing in it.
        """
        if augment is not None and augment.rotation and not self.config.has_planar_values:
            raise ValueError(
                "augment.rotation turns the ground plane, but the data config marks nothing in it: declare "
                "the [x, y] dims with `planar` (modalities.<name>.planar, target.planar, action.planar) "
                "and map cameras with `top_down: true`, or set augment.rotation=0"
            )
        return WindowLoader(
            self,
            split,
            batch_size,
            shuffle=split == "train" if shuffle is None else shuffle,
            seed=seed,
            rank=rank,
            world_size=world_size,
            drop_last=drop_last,
            augment=augment,
        )


class WindowLoader:
    """Iterates a split in batches; each iteration is one epoch.

    Shuffled loaders draw a permutation from ``(seed, epoch)`` (the epoch advances after each full
    pass, or set it with :meth:`set_epoch`) and give rank ``rank`` of ``world_size`` an equal share
    (the tail that does not divide is dropped, like ``DistributedSampler(drop_last=True)``), so DDP
    ranks step together. Sequential loaders cover every window exactly once across ranks.
    ``augment`` transforms the image modalities of every batch; :meth:`close` stops its worker
    processes (the trainer calls it when training ends). :meth:`WindowDataset.loader` builds one.

    Args:
        dataset (WindowDataset): the windows.
        split (str): ``"train"``, ``"val"`` or ``"test"``.
        batch_size (int): windows per batch.
        shuffle (bool): shuffle per epoch, else sequential.
        seed (int, optional): the shuffle's seed. Defaults to ``0``.
        rank (int, optional): this process's rank. Defaults to ``0``.
        world_size (int, optional): processes sharing the split. Defaults to ``1``.
        drop_last (bool, optional): drop the last, smaller batch; ``None`` (default): when shuffling.
        augment (TrainingAugmentation, optional): the training augmentation applied to every batch.

    Raises:
        ValueError: an unknown split, a rank outside ``[0, world_size)`` or ``batch_size < 1``.
    """

    def __init__(
        self,
        dataset: WindowDataset,
        split: str,
        batch_size: int,
        shuffle: bool,
        seed: int = 0,
        rank: int = 0,
        world_size: int = 1,
        drop_last: bool | None = None,
        augment: TrainingAugmentation | None = None,
    ):
        if split not in SPLIT_NAMES:
            raise ValueError(f"unknown split {split!r}; expected one of {list(SPLIT_NAMES)}")
        if not 0 <= rank < world_size:
            raise ValueError(f"rank must be in [0, world_size={world_size}), found {rank}")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, found {batch_size}")
        self.dataset, self.split, self.batch_size = dataset, split, batch_size
        self.shuffle, self.seed, self.rank, self.world_size = shuffle, seed, rank, world_size
        self.drop_last = shuffle if drop_last is None else drop_last
        self.augment = augment
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Set the epoch the next iteration's permutation and augmentation are drawn for.

        Args:
            epoch (int): the epoch (a resumed run sets the one it stopped in).
        """
        self.epoch = epoch

    def _ids(self) -> torch.Tensor:
        ids = self.dataset.split_windows[self.split]
        if self.shuffle:
            generator = torch.Generator().manual_seed(self.seed * 100_003 + self.epoch)
            ids = ids[torch.randperm(len(ids), generator=generator)]
            ids = ids[: len(ids) // self.world_size * self.world_size]
        return ids[self.rank :: self.world_size]

    def __len__(self) -> int:
        n = len(self._ids())
        return n // self.batch_size if self.drop_last else math.ceil(n / self.batch_size)

    @property
    def batch_making(self) -> str:
        """How a batch is made (:data:`~mmf_rl.datasets.prefetch.BATCH_MAKING`): by a gather, by
        a gather and augmentation drawing from the global RNG, or with augmentation in workers."""
        if self.augment is None or not self.augment.names:  # the turns draw from their own generator
            return "thread_safe"
        return "in_workers" if self.augment.workers else "global_rng"

    def __iter__(self) -> Iterator[TensorDict]:
        ids = self._ids()
        stop = len(ids) // self.batch_size * self.batch_size if self.drop_last else len(ids)
        batches = (
            self.dataset.batch(ids[first : first + self.batch_size], self.split, self._angles(first, stop))
            for first in range(0, stop, self.batch_size)
        )
        if self.augment is not None:
            batches = self.augment.augmented(batches, self.epoch, self.rank)
        yield from batches
        self.epoch += 1

    def _angles(self, first: int, stop: int) -> torch.Tensor | None:
        """The turns of the batch that starts at ``first`` (``None``: not turned)."""
        if self.augment is None:
            return None
        n = min(self.batch_size, stop - first)
        return self.augment.angles(n, self.epoch, first // self.batch_size, self.rank)

    def close(self) -> None:
        """Stop the augmentation's worker processes, if any (iterating again restarts them)."""
        if self.augment is not None:
            self.augment.close()
