"""Augmentation of training batches: image transforms as lerobot users know them
(``image_transforms``), and random turns of the ground plane (``rotation``).

The transforms are lerobot's own :class:`~lerobot.datasets.transforms.ImageTransforms` (torchvision
v2 transforms sampled by ``RandomSubsetApply``), configured with the same names: ``enable``,
``max_num_transforms``, ``random_order`` and ``tfs: {name: {weight, type, kwargs}}`` where ``type``
is a ``torchvision.transforms.v2`` class (``ColorJitter``, ``RandomResizedCrop``, ...) or lerobot's
``SharpnessJitter``. They run on the cached ``uint8`` frames of the training loader only:

* one draw per sample and camera, applied to all ``H`` frames of its window (a v2 transform
  treats leading dims as a batch with one set of parameters), so motion between frames is kept;
* deterministic: each batch draws from its own generator state, seeded by the run's seed, the
  epoch, the batch's position and the rank, so a resumed run replays the same augmentations and
  the model's own random draws are untouched;
* off the training thread by default (``workers``): torchvision draws from the global generator,
  which a thread would share with the training step, but a worker process has its own. It
  augments the batches ahead of the one being trained on, with the same seeds, on one intra-op
  thread (the training step keeps the cores; a worker with the step's thread count oversubscribes
  them and makes training slower than no worker, docs/results.md). The batches are those augmented
  on the training thread, bit for bit unless an image is large enough for torch to split one of a
  transform's float reductions across the training thread's threads (then a pixel may round to
  the neighbouring uint8 value).

``rotation`` turns each training window's ground plane by its own angle, drawn uniformly within
``±rotation`` degrees from a generator seeded like the image transforms: the data config's
``planar`` dims and ``top_down`` cameras (:mod:`mmf_rl.datasets.planar`), turned while the window is
gathered, before normalisation.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import asdict, dataclass, field

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.datasets.worker_pool import WorkerPool
from mmf_rl.keys import ModalitySpec

# Tells the rotation's seeds from the image transforms' (a str would hash differently per process).
_ROTATION_STREAM = 1


def lerobot_default_transforms() -> dict[str, dict]:
    """lerobot's default ``tfs`` (brightness, contrast, saturation, hue, sharpness, affine) as plain data."""
    from lerobot.datasets.transforms import ImageTransformsConfig

    return {name: asdict(tf) for name, tf in ImageTransformsConfig().tfs.items()}


@dataclass
class AugmentConfig:
    """lerobot's ``ImageTransformsConfig`` (same fields, same meaning) plus which images and where
    they are augmented; off by default.

    Args:
        enable (bool, optional): augment the training images (never val or test).
        max_num_transforms (int, optional): how many of ``tfs`` are applied to an image at most (drawn by
            weight). Defaults to ``3``.
        random_order (bool, optional): apply them in random order instead of the order of ``tfs``.
        tfs (dict[str, dict], optional): name → lerobot ``ImageTransformConfig`` (``weight``, ``type``,
            ``kwargs``); lerobot's defaults (brightness, contrast, saturation, hue, sharpness, affine).
        modalities (list[str], optional): the image modalities to augment (default: every image modality).
        rotation (float, optional): turn each training window's ground plane by a random angle within
            ``±rotation`` degrees (``180``: any direction; ``0``: never), whether or not ``enable`` is set.
            The data config says what turns (``planar`` dims, ``top_down`` cameras).
        workers (int, optional): processes that augment the next batches while the model trains on the current
            one (default ``1``); ``0``: on the training thread, between steps. Either way the batches are the
            same (to rounding, see the module's docstring). They start at the first batch, spawned (they
            import torch and lerobot once per run), so a script that trains with them guards its entry point
            with ``if __name__ == "__main__":``.
    """

    enable: bool = False
    max_num_transforms: int = 3
    random_order: bool = False
    tfs: dict[str, dict] = field(default_factory=lerobot_default_transforms)
    modalities: list[str] | None = None
    rotation: float = 0.0
    workers: int = 1

    @classmethod
    def from_dict(cls, d: dict | None) -> AugmentConfig:
        """Build from plain data (the Hydra ``augment`` config), checked.

        Args:
            d (dict, optional): the config's keys; ``None`` or empty: the defaults.

        Returns:
            The config.

        Raises:
            ValueError: an unknown key, ``max_num_transforms < 1``, ``rotation`` outside
                ``[0, 180]`` or ``workers < 0``.
        """
        d = dict(d or {})
        reject_unknown_keys(cls, d, "augment config")
        config = cls(**d)
        for name, tf in config.tfs.items():
            reject_unknown_keys(_transform_config_cls(), dict(tf), f"augment config: tfs.{name}")
        if config.max_num_transforms < 1:
            raise ValueError(
                f"augment config: `max_num_transforms` must be >= 1, found {config.max_num_transforms}"
            )
        if not 0.0 <= config.rotation <= 180.0:
            raise ValueError(
                f"augment config: `rotation` is the largest turn in degrees, in [0, 180] (180: any "
                f"direction), found {config.rotation}"
            )
        if config.workers < 0:
            raise ValueError(
                f"augment config: `workers` must be >= 0 (0: augment on the training thread), found "
                f"{config.workers}"
            )
        return config

    def build(self):
        """lerobot's ``ImageTransforms`` for this config; a bad transform is named by its key."""
        from lerobot.datasets.transforms import (
            ImageTransforms,
            ImageTransformsConfig,
            make_transform_from_config,
        )

        tfs = {name: _transform_config_cls()(**tf) for name, tf in self.tfs.items()}
        for name, tf in tfs.items():
            try:
                make_transform_from_config(tf)
            except (TypeError, ValueError) as error:
                raise ValueError(
                    f"augment config: tfs.{name} (type {tf.type!r}, kwargs {tf.kwargs}): {error}"
                ) from None
        return ImageTransforms(
            ImageTransformsConfig(
                enable=self.enable,
                max_num_transforms=self.max_num_transforms,
                random_order=self.random_order,
                tfs=tfs,
            )
        )


def _transform_config_cls():
    from lerobot.datasets.transforms import ImageTransformConfig

    return ImageTransformConfig


class TrainingAugmentation:
    """Applies an :class:`AugmentConfig` to training batches: the image transforms to the image
    modalities (in place), and the angles the loader turns each window by (:meth:`angles`).

    ``augmented`` augments a stream of batches, in ``config.workers`` processes when it is not 0;
    :meth:`close` stops them (the next stream starts them again).

    Args:
        config (AugmentConfig): what to do.
        specs (list[ModalitySpec]): the data's modalities (the image ones are augmented).
        seed (int): the seed of the transforms' and the turns' draws, with the batch's epoch, index and
            rank: the same run augments the same way.

    Raises:
        ValueError: ``config.modalities`` names a modality that is not an image modality, or a
            transform of ``config.tfs`` cannot be built.
    """

    def __init__(self, config: AugmentConfig, specs: list[ModalitySpec], seed: int):
        images = [s.name for s in specs if s.kind == "image"]
        unknown = sorted(set(config.modalities or []) - set(images))
        if unknown:
            raise ValueError(
                f"augment config: `modalities` names {unknown}, which are not image modalities "
                f"of the data config (its image modalities: {images})"
            )
        chosen = list(config.modalities) if config.modalities is not None else images
        self.names = chosen if config.enable else []  # turning alone transforms no image
        self.transform = config.build()
        self.seed = seed
        self.rotation = math.radians(config.rotation)
        self.workers = config.workers if self.names else 0
        self._make_in_worker = functools.partial(_frames_augmenter, config, specs, seed)
        self._pool: WorkerPool | None = None

    def angles(self, n: int, epoch: int, index: int, rank: int = 0) -> torch.Tensor | None:
        """The ``[n]`` angles (radians) that turn batch ``index`` of ``epoch`` on ``rank``; ``None``
        without ``rotation``. From their own generator: neither the image transforms' draws nor the
        model's depend on them."""
        if not self.rotation:
            return None
        generator = torch.Generator().manual_seed(
            hash((self.seed, epoch, index, rank, _ROTATION_STREAM)) % 2**63
        )
        return (2 * torch.rand(n, generator=generator, dtype=torch.float64) - 1) * self.rotation

    def __call__(self, batch: TensorDictBase, epoch: int, index: int, rank: int = 0) -> TensorDictBase:
        """``batch`` augmented here, on the calling thread."""
        return self._set_frames(batch, self.augment_frames(self._frames(batch), epoch, index, rank))

    def augment_frames(
        self, frames: dict[str, torch.Tensor], epoch: int, index: int, rank: int
    ) -> dict[str, torch.Tensor]:
        """The augmented ``uint8 [B, H, C, h, w]`` frames of each modality, for batch ``index`` of
        ``epoch`` on ``rank``: what a worker process runs, and the calling thread without one."""
        # torchvision draws from the global generator: fork it, so the augmentation neither depends
        # on nor changes the model's draws, and seed it from the batch's place in the run.
        augmented = {}
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(hash((self.seed, epoch, index, rank)) % 2**63)
            for name, windows in frames.items():
                augmented[name] = torch.stack([self.transform(window) for window in windows])
                if augmented[name].shape != windows.shape:
                    raise ValueError(
                        f"augment: the transforms turn {name!r} frames of {list(windows.shape[-2:])} into "
                        f"{list(augmented[name].shape[-2:])}; a transform that resizes (e.g. "
                        "RandomResizedCrop's `size`) must give the data config's image_size"
                    )
        return augmented

    def augmented(
        self, batches: Iterable[TensorDictBase], epoch: int, rank: int = 0
    ) -> Iterator[TensorDictBase]:
        """``batches`` (one epoch, in order) augmented; with workers, ``workers`` batches are made
        and augmenting ahead of the one returned."""
        if self.workers == 0:
            for index, batch in enumerate(batches):
                yield self(batch, epoch, index, rank)
            return
        if self._pool is None or self._pool.closed:
            self._pool = WorkerPool(
                self._make_in_worker,
                self.workers,
                role="image augmentation",
                fix="augment.workers=0 augments on the training thread instead (a process killed by "
                "signal 9 is often the out-of-memory killer's doing)",
            )
        pool, ahead = self._pool, deque()
        for index, batch in enumerate(batches):
            ahead.append((batch, pool.submit(self._frames(batch), epoch, index, rank)))
            if len(ahead) > self.workers:
                batch, ticket = ahead.popleft()
                yield self._set_frames(batch, pool.result(ticket))
        for batch, ticket in ahead:
            yield self._set_frames(batch, pool.result(ticket))

    def close(self) -> None:
        """Stop the worker processes, if any."""
        if self._pool is not None:
            self._pool.close()

    def _frames(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        return {name: batch.get(keys.obs_key(name)) for name in self.names}

    def _set_frames(self, batch: TensorDictBase, frames: dict[str, torch.Tensor]) -> TensorDictBase:
        for name, augmented in frames.items():
            batch.set(keys.obs_key(name), augmented)
        return batch


def _frames_augmenter(config: AugmentConfig, specs: list[ModalitySpec], seed: int):
    """In a worker process: the augmentation's ``augment_frames``, built there once."""
    return TrainingAugmentation(config, specs, seed).augment_frames
