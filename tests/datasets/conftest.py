"""Fixtures: the real SO-101 recording (read-only, cameras absent) and a synthetic dataset."""

import os
import shutil
from pathlib import Path

# Before lerobot/huggingface_hub are imported: nothing in these tests may reach the hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest

from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.synthetic import (
    FORCE_FEATURE,
    IMAGE_FEATURE,
    POSE_FEATURE,
    STATE_FEATURE,
    make_synthetic_dataset,
)

# The shared real recordings sit beside the repository (../shared), in CI as here; a clone on its
# own has none, and the tests that read them skip.
SO101_ROOT = Path(__file__).resolve().parents[3] / "shared" / "data" / "so101_record_test"
needs_so101 = pytest.mark.skipif(not (SO101_ROOT / "meta" / "info.json").is_file(),
                                 reason=f"the real SO-101 recording is not at {SO101_ROOT} (../shared beside the repo)")
# Episode 4 (6 frames) is shorter than history + horizon = 7: it must be skipped.
EPISODE_LENGTHS = [30, 25, 20, 12, 6]
NAN_FORCE_EPISODE = 1  # force is NaN on frames [5, 10)
INVALID_IMAGE_EPISODE = 2  # camera flagged invalid on frames [5, 10)
IMAGE_SIZE = 24


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("synthetic") / "push"
    make_synthetic_dataset(
        root, EPISODE_LENGTHS, image_size=32, nan_force_episodes=(NAN_FORCE_EPISODE,),
        invalid_image_episodes=(INVALID_IMAGE_EPISODE,),
    )
    return root


@pytest.fixture
def synthetic_copy(synthetic_root, tmp_path) -> Path:
    """A private copy, for tests that modify dataset files."""
    return Path(shutil.copytree(synthetic_root, tmp_path / "push_copy"))


def synthetic_config(root, cache_dir, **overrides) -> DataConfig:
    d = {
        "root": str(root),
        "cache_dir": str(cache_dir),
        "history": 4,
        "horizon": 3,
        "image_size": [IMAGE_SIZE, IMAGE_SIZE],
        "split_fractions": [0.6, 0.2, 0.2],
        "modalities": {
            "image": IMAGE_FEATURE,  # its validity feature is found by name (the recorder's convention)
            "state": STATE_FEATURE,
            "force": {"feature": FORCE_FEATURE},
        },
        "target": {"feature": POSE_FEATURE, "dims": [0, 1]},
    }
    d.update(overrides)
    return DataConfig.from_dict(d)


def so101_config(cache_dir, **overrides) -> DataConfig:
    d = {
        "root": str(SO101_ROOT),
        "cache_dir": str(cache_dir),
        "history": 5,
        "horizon": 5,
        "image_size": [16, 16],
        "modalities": {"front": "observation.images.front", "top": "observation.images.top",
                       "state": "observation.state"},
        "target": {"feature": "observation.state", "dims": [0, 1, 2]},
    }
    d.update(overrides)
    return DataConfig.from_dict(d)
