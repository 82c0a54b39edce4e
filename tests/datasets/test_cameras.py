"""Every way LeRobot stores a camera: videos, images in the parquet (RGB and one-channel depth).

The datasets are written by lerobot's own ``LeRobotDataset.create`` with feature names the push
recorder does not use; cached and batched values are checked against what was recorded.
"""

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf, open_dict
from tensordict import TensorDict

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.configuration import compose_config
from mmf_rl.datasets import WindowDataset, lerobot_source
from mmf_rl.datasets.lerobot_source import REPORTED_IMAGE_ERRORS
from mmf_rl.keys import obs_key, present_key
from mmf_rl.trainers.training import train
from tests.datasets.conftest import (
    BROKEN_ROWS,
    CAMERA_EPISODES,
    CAMERA_HEIGHT,
    CAMERA_WIDTH,
    JOINTS,
    VIDEO_CAMERA,
    camera_config,
    camera_frame,
)


def recorded(channels: int, flip: bool = False) -> torch.Tensor:
    """Every recorded frame of a camera in cache layout ``uint8 [N, C, h, w]``, episodes in order."""
    frames = [camera_frame(e, f, channels) for e, n in enumerate(CAMERA_EPISODES) for f in range(n)]
    frames = [f[::-1] if flip else f for f in frames]
    return torch.from_numpy(np.stack(frames)).permute(0, 3, 1, 2)


def cached_frames(dataset: WindowDataset, name: str) -> torch.Tensor:
    return TensorDict.load_memmap(dataset.cache_path / "frames").get(("obs", name)).as_subclass(torch.Tensor)


def test_images_in_the_parquet_are_cached_exactly_rgb_and_depth(image_only_root, tmp_path):
    dataset = WindowDataset(camera_config(image_only_root, tmp_path))
    specs = {s.name: (s.kind, s.shape) for s in dataset.specs}
    assert specs == {
        "wrist": ("image", (3, CAMERA_HEIGHT, CAMERA_WIDTH)),
        "depth": ("image", (1, CAMERA_HEIGHT, CAMERA_WIDTH)),
        "joints": ("sequence", (4,)),
    }
    # PNG is lossless and the cache keeps the recorded size: every value equals the recorded one.
    assert torch.equal(cached_frames(dataset, "wrist"), recorded(3))
    assert torch.equal(cached_frames(dataset, "depth"), recorded(1))
    assert all(mask.all() for mask in dataset.presence.values())
    assert not dataset.report["undecodable_files"] and not dataset.report["missing_files"]

    ids = torch.arange(len(dataset))
    batch = dataset.batch(ids)
    start = dataset.window_start[ids]
    rows = start[:, None] + torch.arange(3)
    assert torch.equal(batch.get(obs_key("wrist")), recorded(3)[rows])
    assert torch.equal(batch.get(obs_key("depth")), recorded(1)[rows])


@pytest.mark.parametrize("workers", [1, pytest.param(2, marks=pytest.mark.slow)])  # 2: a pool of processes
def test_an_undecodable_image_is_an_absent_frame_named_in_the_report(broken_images_root, tmp_path, workers):
    with pytest.warns(
        UserWarning, match=r"'wrist'.*episode 0 frame 1 \(undecodable: RuntimeError: Unsupported"
    ):
        dataset = WindowDataset(camera_config(broken_images_root, tmp_path), num_workers=workers)
    frames = TensorDict.load_memmap(dataset.cache_path / "frames")
    broken = torch.zeros(sum(CAMERA_EPISODES), dtype=torch.bool)
    broken[BROKEN_ROWS] = True
    assert torch.equal(frames.get(present_key("wrist")).as_subclass(torch.Tensor), ~broken)
    assert frames.get(present_key("depth")).all()
    wrist = cached_frames(dataset, "wrist")
    assert not wrist[broken].any() and torch.equal(wrist[~broken], recorded(3)[~broken])
    assert torch.equal(cached_frames(dataset, "depth"), recorded(1))

    # The first ones in frame order, whichever process decoded them.
    first_rows = np.cumsum([0, *CAMERA_EPISODES])
    episodes = [int(np.searchsorted(first_rows, row, side="right")) - 1 for row in BROKEN_ROWS]
    named = [
        f"{broken_images_root / 'data'} episode {e} frame {row - first_rows[e]}"
        for row, e in zip(BROKEN_ROWS, episodes, strict=True)
    ]
    report = dataset.report["undecodable_files"]
    assert list(report) == ["wrist"] and list(report["wrist"]) == named[:REPORTED_IMAGE_ERRORS]
    assert all(error.startswith("RuntimeError: Unsupported image file") for error in report["wrist"].values())


def test_a_depth_camera_resized_stays_one_channel(image_only_root, tmp_path):
    dataset = WindowDataset(camera_config(image_only_root, tmp_path, image_size=[8, 12]))
    frames = cached_frames(dataset, "depth")
    assert frames.shape == (sum(CAMERA_EPISODES), 1, 8, 12)
    reference = torch.nn.functional.interpolate(
        recorded(1).float() / 255, size=(8, 12), mode="bilinear", antialias=True, align_corners=False
    )
    assert (frames.float() / 255 - reference).abs().max() <= 1 / 255


def test_video_and_image_cameras_in_one_dataset(mixed_cameras_root, tmp_path):
    config = camera_config(mixed_cameras_root, tmp_path)
    config.modalities["top"] = type(config.modalities["wrist"])(feature=VIDEO_CAMERA)
    dataset = WindowDataset(config)
    assert {s.name for s in dataset.specs} == {"wrist", "depth", "joints", "top"}
    assert torch.equal(cached_frames(dataset, "wrist"), recorded(3))
    # The video went through a lossy codec: close to what was recorded, and not another frame.
    video = cached_frames(dataset, "top").float()
    error = (video - recorded(3, flip=True).float()).abs().mean()
    assert error < 12, float(error)
    assert error < (video - recorded(3).float()).abs().mean() / 3
    batch = next(iter(dataset.loader("train", batch_size=8)))
    assert all(batch.get(present_key(n)).all() for n in ("wrist", "depth", "top", "joints"))


@pytest.mark.slow  # a training run end to end over every camera storage
def test_training_reads_every_camera_storage_with_augmentation(mixed_cameras_root, tmp_path):
    cfg = compose_config(
        "train",
        [
            f"run_dir={tmp_path / 'run'}",
            "model.d_model=16",
            "model.d_latent=4",
            "model.num_heads=2",
            "model.mlp_hidden=32",
            "model.head_hidden=32",
            "trainer.total_steps=4",
            "trainer.batch_size=8",
            "trainer.eval_every=2",
            "trainer.checkpoint_every=2",
            "trainer.warmup_steps=1",
            "trainer.progress_bar=false",
            "logger=none",
            "num_workers=0",
            "augment=crop",
            "augment.workers=0",  # on the training thread: a worker process gives the same batches
            f"data.image_size=[{CAMERA_HEIGHT},{CAMERA_WIDTH}]",
        ],
    )
    data = camera_config(mixed_cameras_root, tmp_path / "cache").to_dict()
    data["modalities"]["top"] = {"feature": VIDEO_CAMERA}
    with open_dict(cfg):
        cfg.data = OmegaConf.create(data)
    train(cfg)
    checkpoint = load_checkpoint(tmp_path / "run" / "checkpoints")
    assert checkpoint.step == 4
    shapes = {m["name"]: m["shape"] for m in checkpoint.meta["model_config"]["modalities"]}
    assert shapes == {
        "depth": [1, CAMERA_HEIGHT, CAMERA_WIDTH],
        "joints": [4],
        "top": [3, CAMERA_HEIGHT, CAMERA_WIDTH],
        "wrist": [3, CAMERA_HEIGHT, CAMERA_WIDTH],
    }
    assert all(torch.isfinite(v).all() for v in checkpoint.model_state.values())


def test_a_decoder_bug_propagates_instead_of_marking_the_camera_absent(
    mixed_cameras_root, tmp_path, monkeypatch
):
    """Only decode errors mean "camera absent": a TypeError (say, from a lerobot API change) is a bug
    and must surface, not be cached as a camera that is never there."""
    import lerobot.datasets.video_utils

    def changed_api(*args, **kwargs):
        raise TypeError("decode_video_frames_torchcodec() got an unexpected keyword argument")

    monkeypatch.setattr(lerobot.datasets.video_utils, "decode_video_frames_torchcodec", changed_api)
    config = camera_config(mixed_cameras_root, tmp_path, modalities={"cam": VIDEO_CAMERA, "joints": JOINTS})
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        WindowDataset(config, num_workers=1)
    assert not list(tmp_path.glob("*/cache.json")), "no cache records the camera as absent"

    # Storing decoded frames is not decoding: a RuntimeError there is a bug too, not an absent camera.
    monkeypatch.undo()

    def bad_store(*args, **kwargs):
        raise RuntimeError("The size of tensor a (16) must match the size of tensor b (32)")

    monkeypatch.setattr(lerobot_source, "to_cache_frames", bad_store)
    with pytest.raises(RuntimeError, match="must match the size"):
        WindowDataset(config, num_workers=1)
