"""Image augmentation of training batches: lerobot's transforms, one draw per window, seeded."""

import multiprocessing
import os
import signal
import warnings

import pytest
import torch

from mmf_rl.configuration import compose_config, to_container
from mmf_rl.datasets import AugmentConfig, TrainingAugmentation, WindowDataset
from mmf_rl.keys import obs_key
from tests.conftest import SMALL_MODALITIES, make_batch
from tests.datasets.conftest import synthetic_config


def augment_workers() -> list:
    return [p for p in multiprocessing.active_children() if p.name.startswith("mmf-rl-image-augmentation")]


@pytest.fixture(scope="module")
def dataset(synthetic_root, tmp_path_factory):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WindowDataset(synthetic_config(synthetic_root, tmp_path_factory.mktemp("cache")))


def lerobot_augmentation(seed: int = 0, **overrides) -> TrainingAugmentation:
    cfg = to_container(compose_config("train", ["augment=crop", "data.image_size=[16,16]"]).augment)
    return TrainingAugmentation(AugmentConfig.from_dict({**cfg, **overrides}), SMALL_MODALITIES, seed)


def still_windows(seed: int):
    """A batch whose image windows repeat one frame: a window-consistent transform keeps them equal."""
    batch = make_batch(16, seed=seed)
    frames = batch.get(obs_key("image"))
    batch.set(obs_key("image"), frames[:, :1].expand_as(frames).contiguous())
    return batch


def test_one_draw_per_window_changes_images_only(tmp_path):
    augment = lerobot_augmentation()
    batch = still_windows(0)
    before = batch.clone()
    out = augment(batch, epoch=0, index=0)
    images = out.get(obs_key("image"))
    assert images.dtype == torch.uint8 and images.shape == before.get(obs_key("image")).shape
    assert (images == images[:, :1]).all(), "every frame of a window must get the same transform"
    changed = (images != before.get(obs_key("image"))).flatten(1).any(1)
    assert changed.float().mean() > 0.8
    assert torch.equal(out.get(obs_key("force")), before.get(obs_key("force")))


def test_deterministic_under_the_seed_and_independent_of_the_global_generator():
    first = lerobot_augmentation(seed=3)(still_windows(0), epoch=1, index=2)
    torch.manual_seed(12345)
    state = torch.get_rng_state()
    again = lerobot_augmentation(seed=3)(still_windows(0), epoch=1, index=2)
    assert torch.equal(torch.get_rng_state(), state), "augmenting must not consume the model's random draws"
    assert torch.equal(first.get(obs_key("image")), again.get(obs_key("image")))
    for other in ({"seed": 4}, {"epoch": 2}, {"index": 3}):
        augment = lerobot_augmentation(seed=other.get("seed", 3))
        out = augment(still_windows(0), epoch=other.get("epoch", 1), index=other.get("index", 2))
        assert not torch.equal(out.get(obs_key("image")), first.get(obs_key("image"))), other


def test_training_loader_only_and_off_by_default(dataset):
    assert not AugmentConfig.from_dict(to_container(compose_config("train", []).augment)).enable
    # augment=lerobot, on the training thread: a worker process gives the same batches (below).
    cfg = to_container(compose_config("train", ["augment=lerobot", "augment.workers=0"]).augment)
    augment = TrainingAugmentation(AugmentConfig.from_dict(cfg), dataset.specs, seed=0)
    plain = next(iter(dataset.loader("train", 8, seed=1)))
    augmented = next(iter(dataset.loader("train", 8, seed=1, augment=augment)))
    augment.close()
    assert torch.equal(plain.get("target"), augmented.get("target"))
    assert not torch.equal(plain.get(obs_key("image")), augmented.get(obs_key("image")))
    assert torch.equal(
        next(iter(dataset.loader("val", 8))).get(obs_key("image")),
        dataset.batch(dataset.split_windows["val"][:8]).get(obs_key("image")),
    )


def epoch_of(loader, epoch: int, batches: int | None = None) -> list:
    loader.set_epoch(epoch)
    return [batch for _, batch in zip(range(batches or len(loader)), loader, strict=False)]


@pytest.mark.slow
def test_augmenting_in_workers_gives_the_training_threads_batches_bit_for_bit(dataset):
    cfg = to_container(compose_config("train", ["augment=lerobot"]).augment)
    loaders = {
        workers: dataset.loader(
            "train",
            8,
            seed=1,
            augment=TrainingAugmentation(
                AugmentConfig.from_dict({**cfg, "workers": workers}), dataset.specs, 5
            ),
        )
        for workers in (0, 2)
    }
    assert [loaders[w].batch_making for w in (0, 2)] == ["global_rng", "in_workers"]
    assert dataset.loader("train", 8).batch_making == "thread_safe"
    torch.manual_seed(7)
    state = torch.get_rng_state()
    # An epoch left after its first batch (requests in flight): the next epoch's batches are its own.
    epoch_of(loaders[2], epoch=0, batches=1)
    in_workers = epoch_of(loaders[2], epoch=1) + epoch_of(loaders[2], epoch=2)
    assert torch.equal(torch.get_rng_state(), state), "the workers must not touch the model's draws"
    assert len(augment_workers()) == 2
    loaders[2].close()
    assert not augment_workers()
    here = epoch_of(loaders[0], epoch=1) + epoch_of(loaders[0], epoch=2)
    plain = epoch_of(dataset.loader("train", 8, seed=1), epoch=1)
    assert len(in_workers) == len(here) == 2 * len(plain) > 2
    for a, b in zip(in_workers, here, strict=True):
        assert (a == b).all(), "a batch augmented in a worker differs from the training thread's"
    assert not torch.equal(here[0].get(obs_key("image")), plain[0].get(obs_key("image")))


@pytest.mark.slow
def test_a_killed_worker_stops_the_epoch_with_an_error_naming_the_fix(dataset):
    cfg = to_container(compose_config("train", ["augment=lerobot"]).augment)
    loader = dataset.loader(
        "train", 8, augment=TrainingAugmentation(AugmentConfig.from_dict(cfg), dataset.specs, 0)
    )
    batches = iter(loader)
    next(batches)
    (worker,) = augment_workers()
    os.kill(worker.pid, signal.SIGKILL)
    with pytest.raises(
        RuntimeError, match=r"image augmentation worker process .* killed by signal 9; augment.workers=0"
    ):
        list(batches)
    assert not augment_workers()


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"tfs": {"blur": {"type": "NoSuchTransform"}}}, r"tfs.blur \(type 'NoSuchTransform'"),
        ({"tfs": {"jitter": {"type": "ColorJitter", "kwargs": {"brightness": -1}}}}, r"tfs.jitter"),
        ({"tfs": {"jitter": {"kind": "ColorJitter"}}}, r"tfs.jitter: unknown keys \['kind'\]"),
        ({"modalities": ["force"]}, r"names \['force'\], which are not image modalities"),
        ({"strength": 2}, r"unknown keys \['strength'\]"),
        ({"workers": -1}, r"`workers` must be >= 0 \(0: augment on the training thread\), found -1"),
    ],
)
def test_bad_augment_configs_are_named(overrides, message):
    with pytest.raises(ValueError, match=message):
        TrainingAugmentation(AugmentConfig.from_dict({"enable": True, **overrides}), SMALL_MODALITIES, 0)


@pytest.mark.parametrize("workers", [0, pytest.param(1, marks=pytest.mark.slow)])  # 1: a worker process
def test_a_transform_that_resizes_is_named(workers):
    augment = TrainingAugmentation(
        AugmentConfig.from_dict(
            {
                "enable": True,
                "max_num_transforms": 1,
                "tfs": {"crop": {"type": "RandomResizedCrop", "kwargs": {"size": [8, 8]}}},
                "workers": workers,
            }
        ),
        SMALL_MODALITIES,
        0,
    )
    try:
        with pytest.raises(ValueError, match=r"'image' frames of \[16, 16\] into \[8, 8\].*image_size"):
            list(augment.augmented([make_batch(2)], epoch=0))
    finally:
        augment.close()
