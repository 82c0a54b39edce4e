"""A small synthetic LeRobot v3.0 dataset (video + vectors), for the data benchmarks
(``benchmarks/data_throughput.py``, ``benchmarks/cache_scale.py``) and the dataset tests.

A square moves across a camera image while its planar pose is recorded; a force-like vector
has NaN spans (a dropped sensor) and the camera has a validity feature with invalid spans
(a camera that froze), so every presence path of the pipeline has something to find.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

IMAGE_FEATURE = "observation.images.front"
# lerobot 0.4.4 treats any feature whose name contains "image" as a camera when aggregating
# stats, so a per-frame validity flag must be named without it.
IMAGE_VALID_FEATURE = "observation.front_camera_valid"
STATE_FEATURE = "observation.state"
FORCE_FEATURE = "observation.force"
POSE_FEATURE = "observation.object_pose"


def synthetic_features(image_size: int) -> dict:
    return {
        IMAGE_FEATURE: {
            "dtype": "video",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        },
        IMAGE_VALID_FEATURE: {"dtype": "bool", "shape": (1,), "names": None},
        STATE_FEATURE: {"dtype": "float32", "shape": (4,), "names": None},
        FORCE_FEATURE: {"dtype": "float32", "shape": (3,), "names": None},
        POSE_FEATURE: {"dtype": "float32", "shape": (3,), "names": None},
    }


def make_synthetic_dataset(
    root: str | Path,
    episode_lengths: list[int],
    image_size: int = 48,
    fps: int = 25,
    seed: int = 0,
    nan_force_episodes: tuple[int, ...] = (1,),
    invalid_image_episodes: tuple[int, ...] = (2,),
    repo_id: str = "local/mmf_rl_synthetic",
    vcodec: str = "h264",
    video_files_size_in_mb: float | None = None,
):
    """Record a dataset at ``root`` (must not exist) and return the ``LeRobotDataset``.

    Episode ``e`` has ``episode_lengths[e]`` frames. In each episode of ``nan_force_episodes`` the
    force is NaN on frames ``[5, 10)``; in each of ``invalid_image_episodes`` the camera's validity
    flag is False on frames ``[5, 10)``. ``observation.object_pose[0]`` equals
    ``episode_index + frame_index / 1000`` so a window's origin is readable from its values.
    ``video_files_size_in_mb`` caps lerobot's video files (its default: 200 MB).
    """
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    rng = np.random.default_rng(seed)
    dataset = LeRobotDataset.create(
        repo_id=repo_id,
        fps=fps,
        features=synthetic_features(image_size),
        root=root,
        use_videos=True,
        vcodec=vcodec,
    )
    if video_files_size_in_mb is not None:
        dataset.meta.update_chunk_settings(video_files_size_in_mb=video_files_size_in_mb)
    half = 4
    for episode, length in enumerate(episode_lengths):
        start = rng.uniform(half, image_size - half, size=2)
        velocity = rng.uniform(-1.0, 1.0, size=2)
        for frame in range(length):
            in_span = 5 <= frame < 10
            faults = (
                episode in nan_force_episodes and in_span,
                episode in invalid_image_episodes and in_span,
            )
            dataset.add_frame(_synthetic_frame(episode, frame, (start, velocity), image_size, rng, faults))
        dataset.save_episode()
    dataset.finalize()
    return dataset


def _synthetic_frame(
    episode: int,
    frame: int,
    motion: tuple,
    image_size: int,
    rng: np.random.Generator,
    faults: tuple[bool, bool],
) -> dict:
    """Frame ``frame`` of ``episode``: a square moving at constant velocity from ``motion``'s
    ``(start, velocity)``, random force (NaN when ``faults[0]``), the camera flagged invalid when
    ``faults[1]``."""
    half = 4
    start, velocity = motion
    xy = np.clip(start + velocity * frame, half, image_size - half - 1)
    image = np.zeros((image_size, image_size, 3), dtype=np.uint8)
    col, row = int(xy[0]), int(xy[1])
    image[row - half : row + half, col - half : col + half] = (255, 128, 32)
    pose = np.array([episode + frame / 1000.0, xy[1], np.sin(frame / 10.0)], dtype=np.float32)
    state = np.array([xy[0], xy[1], velocity[0], velocity[1]], dtype=np.float32)
    force = rng.normal(size=3).astype(np.float32)
    force_nan, image_invalid = faults
    if force_nan:
        force[:] = np.nan
    return {
        IMAGE_FEATURE: image,
        IMAGE_VALID_FEATURE: np.array([not image_invalid]),
        STATE_FEATURE: state,
        FORCE_FEATURE: force,
        POSE_FEATURE: pose,
        "task": "push the square",
    }
