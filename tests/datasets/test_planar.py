"""Turning the ground plane of training windows: the math, the map convention, the loader, the errors."""

import math
import warnings

import numpy as np
import pytest
import torch

from mmf_rl.datasets import AugmentConfig, TrainingAugmentation, WindowDataset, ethucy
from mmf_rl.datasets.planar import rotate_frames, rotate_pairs
from mmf_rl.keys import TARGET, obs_key
from tests.datasets.conftest import FORCE_FEATURE, STATE_FEATURE, synthetic_config

# The synthetic push data: the target is the object's (x, y); state dims 0, 1 are the gripper's.
PLANAR = {
    "modalities": {
        "image": {"feature": "observation.images.front", "top_down": True},
        "state": {"feature": STATE_FEATURE, "planar": [[0, 1]]},
        "force": {"feature": FORCE_FEATURE},
    },
    "target": {"feature": "observation.object_pose", "dims": [0, 1], "planar": [[0, 1]]},
}


def planar_dataset(root, cache_dir, **changes) -> WindowDataset:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WindowDataset(synthetic_config(root, cache_dir, **{**PLANAR, **changes}), num_workers=0)


def turning(rotation: float = 180.0, seed: int = 0, **augment) -> TrainingAugmentation:
    config = AugmentConfig.from_dict({"rotation": rotation, **augment})
    return TrainingAugmentation(config, [], seed)


def test_each_pair_turns_by_its_samples_angle_and_the_rest_stays():
    values = torch.randn(3, 5, 6)
    angles = torch.tensor([0.0, math.pi / 2, 1.0])
    turned = rotate_pairs(values, [[0, 1], [4, 3]], angles)
    assert torch.equal(turned[0], values[0])
    torch.testing.assert_close(turned[1, :, [0, 1]], torch.stack([-values[1, :, 1], values[1, :, 0]], -1))
    torch.testing.assert_close(turned[1, :, [4, 3]], torch.stack([-values[1, :, 3], values[1, :, 4]], -1))
    torch.testing.assert_close(turned[2, :, [0, 1]].norm(dim=-1), values[2, :, [0, 1]].norm(dim=-1))
    assert torch.equal(turned[..., [2, 5]], values[..., [2, 5]])


def test_frames_turn_as_torchvision_rotates_them_non_square_too():
    from torchvision.transforms.v2 import functional as F

    frames = torch.randint(
        0, 256, (6, 3, 3, 20, 36), dtype=torch.uint8, generator=torch.Generator().manual_seed(0)
    )
    angles = torch.tensor([0.0, 0.3, -1.2, math.pi / 2, 2.5, -math.pi])
    turned = rotate_frames(frames, angles)
    expected = torch.stack(
        [
            F.rotate(w, math.degrees(a), interpolation=F.InterpolationMode.BILINEAR)
            for w, a in zip(frames, angles.tolist(), strict=True)
        ]
    )
    assert torch.equal(turned[0], frames[0])
    assert (turned.int() - expected.int()).abs().max() <= 1  # the same up to rounding


def test_a_turned_map_crop_is_the_crop_of_the_turned_world():
    """Turning the world a quarter counter-clockwise puts east where north was: the turned north-up
    crop is the crop with east up, pixel for pixel (the coded scene spells each pixel's place)."""
    rows, cols = np.meshgrid(np.arange(576), np.arange(720), indexing="ij")
    image = np.stack([rows % 256, cols % 256, rows // 256 * 16 + cols // 256], axis=-1).astype(np.uint8)
    scene, crop = ethucy.Scene(image, None), ethucy.CropConfig(pixels=33, metres=8.25)
    centre = np.array([[5.0, 6.0]])
    north_up = torch.from_numpy(scene.crops(centre, crop)).permute(0, 3, 1, 2)[None]  # [1, 1, 3, p, p]
    east_up = torch.from_numpy(scene.crops(centre, crop, headings=np.array([0.0]))).permute(0, 3, 1, 2)
    turned = rotate_frames(north_up, torch.tensor([math.pi / 2]))[0]
    assert torch.equal(turned, east_up)
    # And the vectors agree: a point 1 m east (4 px right) is 1 m north (4 px up) once turned.
    east = rotate_pairs(torch.tensor([[1.0, 0.0]]), [[0, 1]], torch.tensor([math.pi / 2]))
    torch.testing.assert_close(east, torch.tensor([[0.0, 1.0]]))
    assert torch.equal(turned[0, :, 12, 16], north_up[0, 0, :, 16, 20])


def test_training_batches_turn_planar_values_and_maps_together(synthetic_root, tmp_path):
    dataset = planar_dataset(synthetic_root, tmp_path)
    plain = next(iter(dataset.loader("train", 8, seed=1)))
    augment = turning(seed=2)
    turned = next(iter(dataset.loader("train", 8, seed=1, augment=augment)))
    angles = augment.angles(8, epoch=0, index=0)
    norm = dataset.normalizer
    target = norm.denormalize_target(turned.get(TARGET))
    expected = rotate_pairs(norm.denormalize_target(plain.get(TARGET)), [[0, 1]], angles)
    torch.testing.assert_close(target, expected, rtol=1e-4, atol=1e-4)
    state = turned.get(obs_key("state")) * norm.stats["state/std"] + norm.stats["state/mean"]
    plain_state = plain.get(obs_key("state")) * norm.stats["state/std"] + norm.stats["state/mean"]
    torch.testing.assert_close(state, rotate_pairs(plain_state, [[0, 1]], angles), rtol=1e-4, atol=1e-4)
    assert torch.equal(turned.get(obs_key("force")), plain.get(obs_key("force")))  # not planar: unturned
    images = turned.get(obs_key("image"))
    assert torch.equal(images, rotate_frames(plain.get(obs_key("image")), angles))
    assert not torch.equal(images, plain.get(obs_key("image")))


def test_turns_are_seeded_per_batch_and_leave_the_global_generator_alone(synthetic_root, tmp_path):
    dataset = planar_dataset(synthetic_root, tmp_path)
    torch.manual_seed(7)
    state = torch.get_rng_state()
    first = [b.get(TARGET) for b in dataset.loader("train", 4, seed=1, augment=turning(seed=3))]
    assert torch.equal(torch.get_rng_state(), state)
    again = [b.get(TARGET) for b in dataset.loader("train", 4, seed=1, augment=turning(seed=3))]
    other = [b.get(TARGET) for b in dataset.loader("train", 4, seed=1, augment=turning(seed=4))]
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(first, other, strict=True))
    angles = turning(seed=3).angles(1000, epoch=0, index=0)
    assert angles.abs().max() <= math.pi and angles.min() < -2.5 and angles.max() > 2.5
    assert turning(rotation=10.0).angles(1000, 0, 0).abs().max() <= math.radians(10.0)
    assert turning(rotation=0.0).angles(4, 0, 0) is None


def test_rotation_alone_leaves_images_unaugmented_and_needs_no_worker(synthetic_root, tmp_path):
    dataset = planar_dataset(
        synthetic_root,
        tmp_path,
        modalities={**PLANAR["modalities"], "image": {"feature": "observation.images.front"}},
    )
    augment = turning(workers=1)
    loader = dataset.loader("train", 8, seed=1, augment=augment)
    assert augment.names == [] and augment.workers == 0 and loader.batch_making == "thread_safe"
    plain = next(iter(dataset.loader("train", 8, seed=1)))
    assert torch.equal(next(iter(loader)).get(obs_key("image")), plain.get(obs_key("image")))


def test_rotation_without_planar_values_is_refused(synthetic_root, tmp_path):
    dataset = planar_dataset(
        synthetic_root,
        tmp_path,
        modalities={"state": STATE_FEATURE},
        target={"feature": "observation.object_pose", "dims": [0, 1]},
    )
    with pytest.raises(ValueError, match=r"augment.rotation turns the ground plane, but the data config"):
        dataset.loader("train", 8, augment=turning())
    with pytest.raises(ValueError, match=r"`rotation` .* in \[0, 180\]"):
        AugmentConfig.from_dict({"rotation": 270})


@pytest.mark.parametrize(
    "modality, target_planar, message",
    [
        (
            {"feature": STATE_FEATURE, "planar": [[0, 4]]},
            None,
            r"modalities.state.planar` pair \[0, 4\] must index the 4",
        ),
        ({"feature": STATE_FEATURE, "planar": [[0, 1], [1, 2]]}, None, r"pair \[1, 2\] reuses a dim"),
        (
            {"feature": STATE_FEATURE, "planar": [[0, 1]], "raw_dims": [1]},
            None,
            r"reuses a dim .* `raw_dims` \[1\]",
        ),
        (
            {"feature": STATE_FEATURE, "planar": [[0, 1, 2]]},
            None,
            r"\[x, y\] pairs of two dims, found \[0, 1, 2\]",
        ),
        ({"feature": STATE_FEATURE, "top_down": True}, None, r"`modalities.state.top_down` is for cameras"),
        ({"feature": STATE_FEATURE}, [[0, 2]], r"`target.planar` pair \[0, 2\] must index the 2 dims"),
    ],
)
def test_bad_planar_declarations_are_named(synthetic_root, tmp_path, modality, target_planar, message):
    target = {"feature": "observation.object_pose", "dims": [0, 1], "planar": target_planar}
    with pytest.raises(ValueError, match=message):
        planar_dataset(synthetic_root, tmp_path, modalities={"state": modality}, target=target)


def test_a_camera_with_planar_dims_is_refused(synthetic_root, tmp_path):
    camera = {"feature": "observation.images.front", "planar": [[0, 1]]}
    with pytest.raises(
        ValueError, match=r"`modalities.image.planar` names dims of a camera; .* `top_down: true`"
    ):
        planar_dataset(synthetic_root, tmp_path, modalities={"image": camera, "state": STATE_FEATURE})
