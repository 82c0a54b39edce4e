"""Image augmentation of training batches, as lerobot users know it (``image_transforms``).

The transforms are lerobot's own :class:`~lerobot.datasets.transforms.ImageTransforms` (torchvision
v2 transforms sampled by ``RandomSubsetApply``), configured with the same names: ``enable``,
``max_num_transforms``, ``random_order`` and ``tfs: {name: {weight, type, kwargs}}`` where ``type``
is a ``torchvision.transforms.v2`` class (``ColorJitter``, ``RandomResizedCrop``, ...) or lerobot's
``SharpnessJitter``. They run on the cached ``uint8`` frames of the training loader only:

* one draw per sample and camera, applied to all ``H`` frames of its window (a v2 transform
  treats leading dims as a batch with one set of parameters), so motion between frames is kept;
* deterministic: each batch draws from its own generator state, seeded by the run's seed, the
  epoch, the batch's position and the rank, so a resumed run replays the same augmentations and
  the model's own random draws are untouched.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.keys import ModalitySpec


def lerobot_default_transforms() -> dict[str, dict]:
    """lerobot's default ``tfs`` (brightness, contrast, saturation, hue, sharpness, affine) as plain data."""
    from lerobot.datasets.transforms import ImageTransformsConfig

    return {name: asdict(tf) for name, tf in ImageTransformsConfig().tfs.items()}


@dataclass
class AugmentConfig:
    """lerobot's ``ImageTransformsConfig`` (same fields, same meaning), off by default.

    Args:
        enable: augment the training images (never val or test).
        max_num_transforms: how many of ``tfs`` are applied to an image at most (drawn by weight).
        random_order: apply them in random order instead of the order of ``tfs``.
        tfs: name → lerobot ``ImageTransformConfig`` (``weight``, ``type``, ``kwargs``); lerobot's
            defaults (brightness, contrast, saturation, hue, sharpness, affine).
        modalities: the image modalities to augment (default: every image modality).
    """

    enable: bool = False
    max_num_transforms: int = 3
    random_order: bool = False
    tfs: dict[str, dict] = field(default_factory=lerobot_default_transforms)
    modalities: list[str] | None = None

    @classmethod
    def from_dict(cls, d: dict | None) -> AugmentConfig:
        d = dict(d or {})
        reject_unknown_keys(cls, d, "augment config")
        config = cls(**d)
        for name, tf in config.tfs.items():
            reject_unknown_keys(_transform_config_cls(), dict(tf), f"augment config: tfs.{name}")
        if config.max_num_transforms < 1:
            raise ValueError(
                f"augment config: `max_num_transforms` must be >= 1, found {config.max_num_transforms}"
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


class ImageAugmentation:
    """Applies an :class:`AugmentConfig` to the image modalities of training batches (in place)."""

    def __init__(self, config: AugmentConfig, specs: list[ModalitySpec], seed: int):
        images = [s.name for s in specs if s.kind == "image"]
        unknown = sorted(set(config.modalities or []) - set(images))
        if unknown:
            raise ValueError(
                f"augment config: `modalities` names {unknown}, which are not image modalities "
                f"of the data config (its image modalities: {images})"
            )
        self.names = list(config.modalities) if config.modalities is not None else images
        self.transform = config.build()
        self.seed = seed

    def __call__(self, batch: TensorDictBase, epoch: int, index: int, rank: int = 0) -> TensorDictBase:
        # torchvision draws from the global generator: fork it, so the augmentation neither depends
        # on nor changes the model's draws, and seed it from the batch's place in the run.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(hash((self.seed, epoch, index, rank)) % 2**63)
            for name in self.names:
                frames = batch.get(keys.obs_key(name))  # uint8 [B, H, C, h, w]
                augmented = torch.stack([self.transform(window) for window in frames])
                if augmented.shape != frames.shape:
                    raise ValueError(
                        f"augment: the transforms turn {name!r} frames of {list(frames.shape[-2:])} into "
                        f"{list(augmented.shape[-2:])}; a transform that resizes (e.g. RandomResizedCrop's "
                        "`size`) must give the data config's image_size"
                    )
                batch.set(keys.obs_key(name), augmented)
        return batch
