"""Fixtures: the real SO-101 recording (read-only, cameras absent) and a synthetic dataset."""

import os
import shutil
from pathlib import Path

# Before lerobot/huggingface_hub are imported: nothing in these tests may reach the hub.
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import pytest

from benchmarks.synthetic.dataset import (
    FORCE_FEATURE,
    IMAGE_FEATURE,
    POSE_FEATURE,
    STATE_FEATURE,
    make_synthetic_dataset,
)
from mmf_rl.datasets.config import DataConfig

# The shared real recordings sit beside the repository (../shared/data), in CI as here;
# MMF_RL_SHARED_DATA points elsewhere (e.g. from a git worktree).
SHARED_DATA = Path(
    os.environ.get("MMF_RL_SHARED_DATA", Path(__file__).resolve().parents[3] / "shared" / "data")
)
SO101_ROOT = SHARED_DATA / "so101_record_test"
G1_ROOT = SHARED_DATA / "g1_pick_bottle_small"
needs_so101 = pytest.mark.skipif(
    not (SO101_ROOT / "meta" / "info.json").is_file(),
    reason=f"the real SO-101 recording is not at {SO101_ROOT} (../shared beside the repo)",
)
# Episode 4 (6 frames) is shorter than history + horizon = 7: it must be skipped.
EPISODE_LENGTHS = [30, 25, 20, 12, 6]
NAN_FORCE_EPISODE = 1  # force is NaN on frames [5, 10)
INVALID_IMAGE_EPISODE = 2  # camera flagged invalid on frames [5, 10)
IMAGE_SIZE = 24
SYNTHETIC_IMAGE_SIZE = 32  # the recorded frames; IMAGE_SIZE is what the windows resize them to


@pytest.fixture(scope="session")
def g1_root() -> Path:
    """The real humanoid recording (AV1 camera, 26-D joints), read-only."""
    if not (G1_ROOT / "meta" / "info.json").is_file():
        pytest.skip(
            f"real G1 recording not found at {G1_ROOT} (set MMF_RL_SHARED_DATA to the shared data directory)"
        )
    return G1_ROOT


# A wall-clock `timestamp` that drifts from frame_index / fps: a clock 1.37% fast, started 12.3 ms late.
CLOCK_RATE, CLOCK_OFFSET_S = 1.0137, 0.0123


@pytest.fixture(scope="session")
def drifting_g1_root(g1_root, tmp_path_factory) -> Path:
    """A copy of the real G1 recording whose parquet `timestamp` drifts off frame_index / fps the way
    a recorder stamping frames with wall-clock time does (frames and video untouched)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    root = Path(shutil.copytree(g1_root, tmp_path_factory.mktemp("drift") / "g1_drifting"))
    fps = 30
    for path in sorted((root / "data").rglob("*.parquet")):
        table = pq.read_table(path)
        frame = table["frame_index"].to_numpy().astype(np.float64)
        drifted = pa.array((frame / fps * CLOCK_RATE + CLOCK_OFFSET_S).astype(np.float32))
        table = table.set_column(table.schema.get_field_index("timestamp"), "timestamp", drifted)
        pq.write_table(table, path)
    return root


def cut_ethucy_raw(tmp_path: Path, steps: int = 22, agents: int = 4) -> Path:
    """The shared ETH/UCY files' layout under ``tmp_path/raw``, each trajectory file cut to its first
    ``agents`` agents within its first ``steps`` steps (the default: a few 20-step tracks per file, a
    conversion of seconds); the scenes linked one by one, so a test can replace one."""
    from mmf_rl.datasets import ethucy

    source_root, raw = SHARED_DATA / "ethucy", tmp_path / "raw"
    for source in sorted((source_root / "trajectories").glob("*/*.txt")):
        rows = [line.split() for line in source.read_text().splitlines() if line.strip()]
        first = float(rows[0][0])
        rows = [r for r in rows if float(r[0]) < first + steps * ethucy.FRAME_STEP]
        kept = list(dict.fromkeys(r[1] for r in rows))[:agents]
        target = raw / source.relative_to(source_root)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text("".join("\t".join(r) + "\n" for r in rows if r[1] in kept))
    (raw / "scenes").mkdir()
    for scene in set(ethucy.SCENE_OF.values()):
        (raw / "scenes" / scene).symlink_to(source_root / "scenes" / scene)
    return raw


def record_synthetic(root: Path, **options) -> Path:
    """The tests' synthetic dataset at ``root``; ``options`` go to ``make_synthetic_dataset`` (e.g.
    its file layout), everything else is the same for every caller."""
    make_synthetic_dataset(
        root,
        EPISODE_LENGTHS,
        image_size=SYNTHETIC_IMAGE_SIZE,
        nan_force_episodes=(NAN_FORCE_EPISODE,),
        invalid_image_episodes=(INVALID_IMAGE_EPISODE,),
        **options,
    )
    return root


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    return record_synthetic(tmp_path_factory.mktemp("synthetic") / "push")


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
        "modalities": {
            # no video file of either camera is on disk
            "front": {"feature": "observation.images.front", "allow_absent": True},
            "top": {"feature": "observation.images.top", "allow_absent": True},
            "state": "observation.state",
        },
        "target": {"feature": "observation.state", "dims": [0, 1, 2]},
    }
    d.update(overrides)
    return DataConfig.from_dict(d)


# --- a LeRobot dataset with other feature names and every camera storage -----------------------

CAMERA_EPISODES = [12, 10, 11, 9]
CAMERA_HEIGHT, CAMERA_WIDTH = 16, 32
VIDEO_CAMERA = "observation.images.cam_high"  # dtype video (mp4)
IMAGE_CAMERA = "observation.images.wrist"  # dtype image (PNG bytes in the parquet)
DEPTH_CAMERA = "observation.depth"  # dtype image, one channel (lerobot's stats reserve "image" names for RGB)
JOINTS = "observation.joints"


def camera_frame(episode: int, frame: int, channels: int) -> np.ndarray:
    """The ``uint8 [h, w, channels]`` image a camera recorded at (episode, frame): smooth, so a lossy
    video keeps it close, and different for every frame and camera."""
    rows, cols = np.mgrid[:CAMERA_HEIGHT, :CAMERA_WIDTH]
    layers = [20 + rows * 4 + cols * 2 + (23 * frame + 61 * episode + 37 * c) % 100 for c in range(channels)]
    return np.stack(layers, -1).astype(np.uint8)


def joints_at(episode: int, frame: int) -> np.ndarray:
    return np.array(
        [episode + frame / 100, np.sin(frame / 3), np.cos(frame / 4), frame % 3], dtype=np.float32
    )


def make_camera_dataset(root: Path, use_videos: bool) -> Path:
    """Record through ``LeRobotDataset.create``: an RGB and a depth camera stored as images in the
    parquet, with ``use_videos`` also a video camera, 4-D joints and a 4-D action."""
    import PIL.Image
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    camera = {"shape": (CAMERA_HEIGHT, CAMERA_WIDTH, 3), "names": ["height", "width", "channels"]}
    features = {
        IMAGE_CAMERA: {"dtype": "image", **camera},
        DEPTH_CAMERA: {
            "dtype": "image",
            "shape": (CAMERA_HEIGHT, CAMERA_WIDTH, 1),
            "names": ["height", "width", "channels"],
        },
        JOINTS: {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
    }
    if use_videos:
        features[VIDEO_CAMERA] = {"dtype": "video", **camera}
    dataset = LeRobotDataset.create(
        repo_id="local/cameras", fps=10, features=features, root=root, use_videos=use_videos, vcodec="h264"
    )
    for episode, length in enumerate(CAMERA_EPISODES):
        for frame in range(length):
            values = {
                IMAGE_CAMERA: camera_frame(episode, frame, 3),
                # lerobot writes a one-channel image only from a PIL image ("L": 8-bit grey)
                DEPTH_CAMERA: PIL.Image.fromarray(camera_frame(episode, frame, 1)[..., 0], mode="L"),
                JOINTS: joints_at(episode, frame),
                "action": joints_at(episode, frame + 1),
                "task": "reach",
            }
            if use_videos:
                values[VIDEO_CAMERA] = camera_frame(episode, frame, 3)[::-1].copy()
            dataset.add_frame(values)
        dataset.save_episode()
    dataset.finalize()
    return root


@pytest.fixture(scope="session")
def image_only_root(tmp_path_factory) -> Path:
    return make_camera_dataset(tmp_path_factory.mktemp("cameras") / "images", use_videos=False)


# Rows (frames, episodes in order) whose wrist image `break_images` replaces: in every episode, and
# more of them than a cache report names.
BROKEN_ROWS = [1, 5, 13, 14, 15, 16, 17, 23, 24, 30, 34, 40]


def break_images(root: Path, rows: list[int]) -> Path:
    """Replace the PNG bytes of the wrist camera at ``rows`` of the dataset at ``root`` by bytes that
    are no image (the rest of the parquet file, its schema and metadata unchanged)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    [data_file] = (root / "data").glob("*/*.parquet")
    table = pq.read_table(data_file)
    assert table.column("index").to_pylist() == list(range(sum(CAMERA_EPISODES)))
    images = table.column(IMAGE_CAMERA).to_pylist()
    for row in rows:
        images[row] = {**images[row], "bytes": b"not an image"}
    field = table.schema.field(IMAGE_CAMERA)
    table = table.set_column(table.schema.get_field_index(IMAGE_CAMERA), field, pa.array(images, field.type))
    pq.write_table(table, data_file)
    return root


def differing_files(a: Path, b: Path) -> list[str]:
    """The files (relative paths) that only one of directories ``a`` and ``b`` holds or whose bytes differ."""
    files = {str(p.relative_to(d)) for d in (a, b) for p in d.rglob("*") if p.is_file()}
    return sorted(
        f
        for f in files
        if not ((a / f).is_file() and (b / f).is_file() and (a / f).read_bytes() == (b / f).read_bytes())
    )


@pytest.fixture(scope="session")
def broken_images_root(image_only_root, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("cameras") / "broken"
    shutil.copytree(image_only_root, root)
    return break_images(root, BROKEN_ROWS)


@pytest.fixture(scope="session")
def mixed_cameras_root(tmp_path_factory) -> Path:
    return make_camera_dataset(tmp_path_factory.mktemp("cameras") / "mixed", use_videos=True)


def camera_config(root, cache_dir, **overrides) -> DataConfig:
    d = {
        "root": str(root),
        "cache_dir": str(cache_dir),
        "history": 3,
        "horizon": 2,
        "image_size": [CAMERA_HEIGHT, CAMERA_WIDTH],
        "split_fractions": [0.5, 0.25, 0.25],
        "modalities": {"wrist": IMAGE_CAMERA, "depth": DEPTH_CAMERA, "joints": JOINTS},
        "target": {"feature": JOINTS, "dims": [0, 1]},
    }
    d.update(overrides)
    return DataConfig.from_dict(d)


# --- a recording named like issue 55's: `state`, `actions`, a camera `image`, videos under `video/` ---

UNCONVENTIONAL_EPISODES = [10, 9, 11, 10, 8, 10, 9, 10]
UNCONVENTIONAL_STATE, UNCONVENTIONAL_ACTIONS, UNCONVENTIONAL_CAMERA = "state", "actions", "image"


def make_unconventional_dataset(root: Path) -> Path:
    """Record through ``LeRobotDataset.create`` a dataset whose features are not named `observation.*`:
    ``actions`` (the commands, listed first) and ``state`` (4-D each) and a video camera ``image``,
    one video file per episode (lerobot starts a new file once one passes ``video_files_size_in_mb``)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    vector = {"dtype": "float32", "shape": (4,), "names": None}
    features = {
        UNCONVENTIONAL_ACTIONS: vector,
        UNCONVENTIONAL_STATE: vector,
        UNCONVENTIONAL_CAMERA: {
            "dtype": "video",
            "shape": (CAMERA_HEIGHT, CAMERA_WIDTH, 3),
            "names": ["height", "width", "channels"],
        },
    }
    dataset = LeRobotDataset.create(
        repo_id="local/unconventional", fps=10, features=features, root=root, use_videos=True, vcodec="h264"
    )
    dataset.meta.update_chunk_settings(video_files_size_in_mb=0.001)
    for episode, length in enumerate(UNCONVENTIONAL_EPISODES):
        for frame in range(length):
            dataset.add_frame(
                {
                    UNCONVENTIONAL_STATE: joints_at(episode, frame),
                    UNCONVENTIONAL_ACTIONS: joints_at(episode, frame + 1),
                    UNCONVENTIONAL_CAMERA: camera_frame(episode, frame, 3),
                    "task": "reach",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return root


@pytest.fixture(scope="session")
def unconventional_root(tmp_path_factory) -> Path:
    """The unconventional recording with its videos committed under ``video/`` while info.json's
    ``video_path`` says ``videos/``: the camera is absent on every frame where training looks."""
    root = make_unconventional_dataset(tmp_path_factory.mktemp("unconventional") / "bimanual")
    (root / "videos").rename(root / "video")
    return root
