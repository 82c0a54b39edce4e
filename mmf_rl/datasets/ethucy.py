"""ETH/UCY pedestrian trajectories -> one LeRobot v3.0 dataset, the five leave-one-scene-out folds
as five data configs over it.

Every file a fold reads (each sequence's ``_train`` and ``_val`` file, and the whole file of each
test sequence) is converted once; a fold's data config names its train/val/test episodes and
selects every episode of the dataset, so the five folds share one window cache build too (the
cache key covers the selection, not the split).

Each LeRobot episode is one agent's track segment: consecutive annotated steps of one agent in
one file. An agent that leaves and re-enters gives two episodes, so no window spans the frames
where it was not annotated and nothing is interpolated or zero-filled there. Per frame:

* ``observation.trajectory`` ``[x, y, vx, vy]``: position (metres, the file's world frame) and
  backward-difference velocity (m/s). At a segment's first step the velocity is 0, like the first
  displacement of Social-GAN's relative tracks; a central or forward difference would read a
  future position (the velocity leak).
* ``observation.neighbours`` ``[K * S * 5]``: the K nearest other agents annotated at that frame,
  nearest first, each a slot of its last S steps (oldest first), every step ``[dx, dy, dvx, dvy,
  seen]`` relative to the agent's state at that frame. A slot is one person over its S steps, so
  an encoder can read where each neighbour is going, not only where someone is at each frame (the
  K nearest are re-chosen every frame). A step where the neighbour was not annotated is zeros with
  ``seen = 0``; the newest step's ``seen`` is the slot's validity, and an empty slot is all zeros
  (the data config leaves the ``seen`` dims unnormalised).
* ``observation.images.scene``: a crop of the scene's reference frame centred on the agent
  (north-up, or heading-up), through the world->pixel maps of the data's README;
  ``observation.scene_camera_valid``
  is False for sequences without a reference frame (``crowds_zara03``, ``uni_examples``), whose
  windows then train with the scene absent.

The target is ``observation.trajectory`` dims ``[0, 1]``, relative to the last observed step.

A fold's windows are every 8 + 12 consecutive steps of one track segment: the test set Trajectron++ and
AgentFormer score on. Social-GAN and Social-STGCNN score on fewer, only the windows another person is
annotated in throughout; `window_set_ids` cuts a split to either set (`WINDOW_SETS`).

The files are written by one process per core (``--workers``), each a contiguous share of them
into a shard dataset, joined in order by lerobot's `aggregate_datasets`: lerobot's per-frame and
per-episode writes cost the time, and the dataset is the same for any number of processes. By
default a process needs `MIN_ROWS_PER_WORKER` rows to start: a small input is written in this one. All of
it happens in a temp dir under ``--out`` renamed into place, so a failed or killed conversion
leaves no dataset; the next one removes what a killed one left and starts over.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import yaml

from mmf_rl.configuration import report_command_error, write_text_atomic
from mmf_rl.datasets.config import DataConfig
from mmf_rl.shards import ShardError, join_shards, run_shards
from mmf_rl.temp_dirs import staging_dir

if TYPE_CHECKING:
    import torch

    from mmf_rl.datasets.windows import WindowDataset

logger = logging.getLogger(__name__)

STEP_S = 0.4  # every 10 video frames at 25 fps, the literature's step for every file
FRAME_STEP = 10  # raw frame numbers between consecutive steps
SLOT_DIM = 5  # per neighbour step: dx, dy, dvx, dvy, seen
TRAJECTORY_KEY = "observation.trajectory"
NEIGHBOURS_KEY = "observation.neighbours"
SCENE_KEY = "observation.images.scene"
SCENE_VALID_KEY = "observation.scene_camera_valid"
AGENT_KEY = "ethucy.agent"
FRAME_KEY = "ethucy.frame"
HISTORY, HORIZON = 8, 12
DATASET_NAME = "ethucy"  # the dataset folder under --out
STAGING_PREFIX = f".{DATASET_NAME}.partial-"  # a conversion's temp dir under --out, renamed when done
# Rows (annotated agent steps) per conversion process for the default to start one: each process
# imports torch and lerobot and aggregate_datasets joins their shards, seconds a small input does not
# win back. Chosen from one process / two: 8 s / 17 s on the tests' 940-row cut, 6 / 3 min on all
# 141k rows (about 2.5 ms a row, 10 s more for two): even at about 8000 rows, so two from 10000.
MIN_ROWS_PER_WORKER = 5000
# numpy's histogram (lerobot's episode stats) warns once per episode about the bool scene flag.
BOOL_STATS_WARNING = re.escape("Converting input from bool to <class 'numpy.uint8'>")

# Leave-one-scene-out: the test scene's whole files; every other sequence's _train/_val files.
FOLDS: dict[str, tuple[str, ...]] = {
    "eth": ("biwi_eth",),
    "hotel": ("biwi_hotel",),
    "univ": ("students001", "students003"),
    "zara1": ("crowds_zara01",),
    "zara2": ("crowds_zara02",),
}
SEQUENCES = (
    "biwi_eth",
    "biwi_hotel",
    "crowds_zara01",
    "crowds_zara02",
    "crowds_zara03",
    "students001",
    "students003",
    "uni_examples",
)
SCENE_OF = {
    "biwi_eth": "seq_eth",
    "biwi_hotel": "seq_hotel",
    "crowds_zara01": "zara01",
    "crowds_zara02": "zara02",
    "students001": "students03",
    "students003": "students03",
}
# UCY trajectories are an exact affine map of the pixel annotations (top-left origin).
UCY_COL = (360.0, 7.5767, 0.021047)
UCY_ROW = (288.0, 6.8734, 0.023866)
# The windows a fold is scored on. Both sets are the literature's; a published figure compares with a
# score on its own set only (docs/benchmarks/ethucy.md).
WINDOW_SETS = {
    "trajectron": "every window of 20 consecutive annotated steps of one agent (Trajectron++, AgentFormer)",
    "social_gan": "the trajectron windows whose 20 frames another agent is annotated in throughout "
    "(Social-GAN, Social-STGCNN)",
}
SOCIAL_GAN_MIN_AGENTS = 2  # Social-GAN keeps frames with more than `min_ped = 1` person in all of them


class ConversionError(RuntimeError):
    """A file (part) that could not be converted, named; nothing was written to ``out/ethucy``."""


class PartError(Exception):
    """`write_dataset`'s failure in one part: the part and what went wrong (picklable: a worker
    process reports it to `convert`, which names the part's file)."""

    def __init__(self, part: str, detail: str):
        super().__init__(part, detail)
        self.part, self.detail = part, detail


@dataclass(frozen=True)
class CropConfig:
    """The scene crop: ``pixels`` square, covering ``metres`` on a side; north-up in world axes, or
    with ``heading`` the agent's direction of motion up (its last known one while it stands)."""

    pixels: int = 64
    metres: float = 8.0
    heading: bool = False


@dataclass(frozen=True)
class NeighbourConfig:
    """The ``count`` nearest agents per frame, each with its last ``steps`` steps (1: that frame only)."""

    count: int = 8
    steps: int = 1

    def __post_init__(self):
        if self.count < 1 or self.steps < 1:
            raise ValueError(
                f"--neighbours {self.count} --neighbour-steps {self.steps}: expected at least 1 agent "
                "and 1 step"
            )

    @property
    def slot_dim(self) -> int:
        return self.steps * SLOT_DIM


@dataclass(frozen=True)
class Scene:
    """One reference frame and its world (metres) -> pixel ``(row, col)`` map."""

    image: np.ndarray  # uint8 [h, w, 3]
    world_to_image: np.ndarray | None  # inverse homography (ETH), or None for the UCY affine map

    def to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """``[..., 2]`` world metres -> ``[..., 2]`` float ``(row, col)``."""
        if self.world_to_image is None:
            col = UCY_COL[0] + (xy[..., 0] - UCY_COL[1]) / UCY_COL[2]
            row = UCY_ROW[0] - (xy[..., 1] - UCY_ROW[1]) / UCY_ROW[2]
            return np.stack([row, col], axis=-1)
        homogeneous = np.concatenate([xy, np.ones_like(xy[..., :1])], axis=-1) @ self.world_to_image.T
        return homogeneous[..., :2] / homogeneous[..., 2:]

    def crops(self, centres: np.ndarray, crop: CropConfig, headings: np.ndarray | None = None) -> np.ndarray:
        """``uint8 [N, p, p, 3]`` nearest-pixel crops centred on ``centres`` ``[N, 2]``; black outside.

        ``headings`` ``[N]`` (radians from +x) is the world direction shown up; default north (+y).
        """
        p, res = crop.pixels, crop.metres / crop.pixels
        offsets = (np.arange(p) - (p - 1) / 2) * res
        angle = np.full(len(centres), np.pi / 2) if headings is None else np.asarray(headings)
        up = np.stack([np.cos(angle), np.sin(angle)], axis=-1)[:, None, None, :]  # [N, 1, 1, 2]
        right = np.stack([np.sin(angle), -np.cos(angle)], axis=-1)[:, None, None, :]
        # Output row i, column j shows world centre + offsets[j] * right - offsets[i] * up.
        world = (
            centres[:, None, None, :]
            + offsets[None, None, :, None] * right
            - offsets[None, :, None, None] * up
        )
        pixels = np.rint(self.to_pixel(world)).astype(np.int64)
        h, w = self.image.shape[:2]
        inside = (pixels[..., 0] >= 0) & (pixels[..., 0] < h) & (pixels[..., 1] >= 0) & (pixels[..., 1] < w)
        rows, cols = np.clip(pixels[..., 0], 0, h - 1), np.clip(pixels[..., 1], 0, w - 1)
        return self.image[rows, cols] * inside[..., None].astype(np.uint8)


def headings(velocities: np.ndarray, min_speed: float = 0.1) -> np.ndarray:
    """``[N]`` direction of motion of one track's ``[N, 2]`` past-only velocities; below ``min_speed``
    (m/s) the last direction it had (north before it first moves)."""
    angle = pd.Series(np.arctan2(velocities[:, 1], velocities[:, 0]))
    angle[np.hypot(velocities[:, 0], velocities[:, 1]) < min_speed] = np.nan
    return angle.ffill().fillna(np.pi / 2).to_numpy()


def load_scene(raw_dir: Path, name: str) -> Scene:
    """The reference frame of scene ``name`` with its world->pixel map."""
    from PIL import Image

    folder = Path(raw_dir) / "scenes" / name
    image = np.asarray(Image.open(folder / "reference.png").convert("RGB"))
    if name in ("seq_eth", "seq_hotel"):
        homography = np.loadtxt(folder / "H.txt")
        if homography.shape != (3, 3):
            raise ValueError(f"{folder / 'H.txt'}: expected a 3x3 homography, found shape {homography.shape}")
        return Scene(image, np.linalg.inv(homography))
    return Scene(image, None)


def read_sequence(path: Path) -> pd.DataFrame:
    """A trajectory file as ``frame, agent, x, y`` (frame and agent as int), sorted, checked."""
    table = pd.read_csv(path, sep=r"\s+", header=None, names=["frame", "agent", "x", "y"], dtype=float)
    if table.isna().any().any() or len(table) == 0:
        raise ValueError(
            f"{path}: expected non-empty rows of 4 numbers `frame agent x y` (tab-separated), found empty "
            "or missing fields; restore the file from the ETH/UCY release"
        )
    table[["frame", "agent"]] = table[["frame", "agent"]].round().astype(np.int64)
    if table.duplicated(["frame", "agent"]).any():
        raise ValueError(
            f"{path}: an agent is annotated twice in one frame; expected one row per (frame, agent)"
        )
    return table.sort_values(["frame", "agent"], ignore_index=True)


def with_velocities(table: pd.DataFrame) -> pd.DataFrame:
    """Add ``vx, vy`` (m/s) by backward difference, 0 where the previous step is not annotated."""
    table = table.sort_values(["agent", "frame"], ignore_index=True)
    previous = table.groupby("agent")[["frame", "x", "y"]].shift(1)
    follows = (table["frame"] - previous["frame"]) == FRAME_STEP
    for axis in ("x", "y"):
        table[f"v{axis}"] = np.where(follows, (table[axis] - previous[axis]) / STEP_S, 0.0)
    table["segment"] = (~follows).groupby(table["agent"]).cumsum()
    return table.sort_values(["frame", "agent"], ignore_index=True)


def neighbour_slots(table: pd.DataFrame, neighbours: NeighbourConfig) -> np.ndarray:
    """``float32 [len(table), K * S * 5]``: per row, its K nearest co-annotated agents (same frame),
    each with its last S steps relative to the row's agent at that frame."""
    nearest = nearest_agents(table, neighbours.count)
    state = table[["x", "y", "vx", "vy"]].to_numpy()
    agents, frames = table["agent"].to_numpy(), table["frame"].to_numpy()
    annotated = pd.MultiIndex.from_arrays([agents, frames])
    neighbour_agents = agents[nearest].ravel()  # garbage where nearest is -1: never seen below
    out = np.zeros((len(table), neighbours.count, neighbours.steps, SLOT_DIM), dtype=np.float32)
    for step in range(neighbours.steps):
        back = (neighbours.steps - 1 - step) * FRAME_STEP
        wanted = pd.MultiIndex.from_arrays([neighbour_agents, np.repeat(frames - back, neighbours.count)])
        row = annotated.get_indexer(wanted).reshape(nearest.shape)
        seen = (nearest >= 0) & (row >= 0)
        relative = state[row] - state[:, None, :]
        out[:, :, step, :4] = np.where(seen[..., None], relative, 0.0)
        out[:, :, step, 4] = seen
    return out.reshape(len(table), -1)


def nearest_agents(table: pd.DataFrame, count: int) -> np.ndarray:
    """``int [len(table), count]``: per row, the rows of its ``count`` nearest co-annotated agents
    (same frame), nearest first; -1 where fewer agents are there."""
    nearest = np.full((len(table), count), -1, dtype=np.int64)
    xy = table[["x", "y"]].to_numpy()
    for rows in table.groupby("frame").indices.values():
        if len(rows) < 2:
            continue
        offset = xy[rows][None, :, :] - xy[rows][:, None, :]  # [agent, other, 2]
        distance = np.hypot(offset[..., 0], offset[..., 1])
        np.fill_diagonal(distance, np.inf)
        order = np.argsort(distance, axis=1, kind="stable")[:, : min(count, len(rows) - 1)]
        nearest[rows, : order.shape[1]] = rows[order]
    return nearest


def dataset_features(neighbours: NeighbourConfig, crop: CropConfig) -> dict[str, dict]:
    slot_names = [
        f"n{k}.{f}" if neighbours.steps == 1 else f"n{k}.t{step - neighbours.steps + 1}.{f}"
        for k in range(neighbours.count)
        for step in range(neighbours.steps)
        for f in ("dx", "dy", "dvx", "dvy", "valid" if neighbours.steps == 1 else "seen")
    ]
    return {
        TRAJECTORY_KEY: {"dtype": "float32", "shape": (4,), "names": ["x", "y", "vx", "vy"]},
        NEIGHBOURS_KEY: {"dtype": "float32", "shape": (len(slot_names),), "names": slot_names},
        SCENE_KEY: {
            "dtype": "image",
            "shape": (crop.pixels, crop.pixels, 3),
            "names": ["height", "width", "channels"],
        },
        SCENE_VALID_KEY: {"dtype": "bool", "shape": (1,), "names": ["valid"]},
        AGENT_KEY: {"dtype": "int64", "shape": (1,), "names": ["agent"]},
        FRAME_KEY: {"dtype": "int64", "shape": (1,), "names": ["frame"]},
    }


def sequence_episodes(
    table: pd.DataFrame, scene: Scene | None, neighbours: NeighbourConfig, crop: CropConfig, min_length: int
) -> list[dict[str, np.ndarray]]:
    """One file's track segments of at least ``min_length`` steps, each a dict of per-frame arrays.

    Neighbours come from the whole file, so a short segment still counts as someone's neighbour.
    """
    table = with_velocities(table)
    slots = neighbour_slots(table, neighbours)
    episodes = []
    for _track, rows in sorted(table.groupby(["agent", "segment"]).indices.items()):
        if len(rows) < min_length:
            continue
        rows = rows[np.argsort(table["frame"].to_numpy()[rows])]
        part = table.iloc[rows]
        centres = part[["x", "y"]].to_numpy()
        images = (
            scene.crops(centres, crop, headings(part[["vx", "vy"]].to_numpy()) if crop.heading else None)
            if scene is not None
            else np.zeros((len(rows), crop.pixels, crop.pixels, 3), dtype=np.uint8)
        )
        episodes.append(
            {
                TRAJECTORY_KEY: part[["x", "y", "vx", "vy"]].to_numpy(np.float32),
                NEIGHBOURS_KEY: slots[rows],
                SCENE_KEY: images,
                SCENE_VALID_KEY: np.full((len(rows), 1), scene is not None),
                AGENT_KEY: part[["agent"]].to_numpy(np.int64),
                FRAME_KEY: part[["frame"]].to_numpy(np.int64),
            }
        )
    return episodes


def track_windows(table: pd.DataFrame, span: int = HISTORY + HORIZON) -> pd.DataFrame:
    """The ``trajectron`` windows of one file: every ``span`` consecutive annotated steps of one agent's
    track segment (`with_velocities`), as that agent and the window's first frame.

    Args:
        table (pd.DataFrame): the file, as `read_sequence` gives it.
        span (int, optional): steps per window. Defaults to ``HISTORY + HORIZON``.

    Returns:
        ``agent, frame`` per window, by agent, then segment, then first frame.
    """
    tracks = with_velocities(table).sort_values(["agent", "segment", "frame"])
    steps_after = tracks.groupby(["agent", "segment"]).cumcount(ascending=False)
    return tracks.loc[steps_after >= span - 1, ["agent", "frame"]].reset_index(drop=True)


def social_gan_windows(first_frames: np.ndarray) -> np.ndarray:
    """Which of one file's ``trajectron`` windows Social-GAN keeps: those that another agent's window
    of the file shares their frames with.

    Social-GAN slides 20 frames over a file and keeps them when more than one person is annotated in
    every one of them, one window per such person. A window of `track_windows` is one person annotated
    throughout, so two windows share their 20 frames exactly when they start at the same frame.
    Social-GAN's frames are those the file annotates anyone in, so its 20 could span a frame number
    nobody has, which no window here does; on the ETH/UCY files no kept sequence does either (every
    file gives Social-GAN's windows: tests/datasets/test_ethucy.py).
    Written here: the rule lives in Social-GAN's own data loader, which is no installable library, and
    the libraries this project uses do not have it.

    Args:
        first_frames (np.ndarray): ``[N]`` each window's first frame, the windows of one file.

    Returns:
        ``bool [N]``, True for a window Social-GAN keeps.
    """
    _, window_group, group_size = np.unique(first_frames, return_inverse=True, return_counts=True)
    return group_size[window_group] >= SOCIAL_GAN_MIN_AGENTS


def window_set_ids(data: WindowDataset, split: str, window_set: str) -> torch.Tensor:
    """The window ids of ``split`` of a converted ETH/UCY fold ``data`` that ``window_set`` scores.

    A split holds one file per sequence at most (its whole file, or its ``_train`` or ``_val`` part),
    so its windows of one sequence (an episode's task) are one file's.

    Args:
        data (WindowDataset): a fold of `convert`'s dataset.
        split (str): ``"train"``, ``"val"`` or ``"test"``.
        window_set (str): a key of `WINDOW_SETS`.

    Returns:
        ``long [N]``: the ids, a subset of ``data.split_windows[split]`` in its order.

    Raises:
        ValueError: an unknown ``window_set``.
    """
    if window_set not in WINDOW_SETS:
        raise ValueError(f"unknown ETH/UCY window set {window_set!r}; expected one of {sorted(WINDOW_SETS)}")
    ids = data.split_windows[split]
    if window_set == "trajectron":
        return ids
    import torch

    from mmf_rl.datasets.lerobot_source import open_metadata, read_frame_columns

    columns = read_frame_columns(
        open_metadata(data.config), ["episode_index", "frame_index", "task_index", FRAME_KEY]
    )
    frames = pd.DataFrame(
        {
            "episode": columns["episode_index"],
            "step": columns["frame_index"],
            "task": columns["task_index"],
            "frame": columns[FRAME_KEY].ravel(),
        }
    )
    first_row = {episode: start for episode, start, _ in data.report["episodes"]}  # in the window cache
    episodes = data.window_episode[ids].numpy()
    steps = data.window_start[ids].numpy() - np.array([first_row[e] for e in episodes], dtype=np.int64)
    windows = pd.DataFrame({"episode": episodes, "step": steps}).merge(
        frames, on=["episode", "step"], how="left", validate="one_to_one"
    )
    kept = np.zeros(len(windows), dtype=bool)
    for rows in windows.groupby("task").indices.values():
        kept[rows] = social_gan_windows(windows["frame"].to_numpy()[rows])
    return ids[torch.from_numpy(kept)]


def fold_files(raw_dir: Path, fold: str) -> dict[str, list[tuple[str, Path]]]:
    """``{split: [(sequence, file)]}`` of a fold, as the data's README tabulates it."""
    if fold not in FOLDS:
        raise ValueError(f"unknown ETH/UCY fold {fold!r}; expected one of {sorted(FOLDS)}")
    trajectories = Path(raw_dir) / "trajectories"
    others = [s for s in SEQUENCES if s not in FOLDS[fold]]
    files = {
        "train": [(s, trajectories / "train" / f"{s}_train.txt") for s in others],
        "val": [(s, trajectories / "val" / f"{s}_val.txt") for s in others],
        "test": [(s, trajectories / "all_data" / f"{s}.txt") for s in FOLDS[fold]],
    }
    absent = [str(p) for entries in files.values() for _, p in entries if not p.is_file()]
    if absent:
        raise FileNotFoundError(
            f"ETH/UCY files missing under {raw_dir}: {absent}; RAW_DIR must hold trajectories/{{train,val,"
            "all_data}/ and scenes/ as in the data's README"
        )
    return files


def write_dataset(
    root: Path,
    tables: dict[str, list[tuple[str, pd.DataFrame]]],
    raw_dir: Path,
    neighbours: NeighbourConfig = NeighbourConfig(),
    crop: CropConfig = CropConfig(),
    min_length: int = HISTORY + HORIZON,
    progress: Callable[[str], None] = logger.info,
) -> dict[str, list[int]]:
    """Write ``{part: [(sequence, table)]}`` as one LeRobot dataset at ``root``; its episodes per part
    (a part is a split, or one converted file). A part that fails raises `PartError` naming it.
    ``progress`` gets a line per converted file.

    Segments shorter than ``min_length`` steps give no window and are left out (they still serve as
    neighbours). Scene crops are stored as images in the parquet files (no video encoding).
    """
    from datasets.utils.logging import disable_progress_bar
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    disable_progress_bar()
    # LeRobot declares fps as an int, but 2.5 Hz is the data's rate and its timestamps follow it.
    dataset = LeRobotDataset.create(
        repo_id=f"local/{Path(root).name}",
        fps=1.0 / STEP_S,
        features=dataset_features(neighbours, crop),
        root=root,
        use_videos=False,
    )
    scenes: dict[str, Scene] = {}
    parts: dict[str, list[int]] = {}
    with warnings.catch_warnings():
        # A bool feature's stats are right after numpy's conversion; the warning would repeat per episode.
        warnings.filterwarnings("ignore", message=BOOL_STATS_WARNING, category=RuntimeWarning)
        for name, entries in tables.items():
            parts[name] = []
            for sequence, table in entries:
                try:
                    scene_name = SCENE_OF.get(sequence)
                    if scene_name is not None and scene_name not in scenes:
                        scenes[scene_name] = load_scene(raw_dir, scene_name)
                    episodes = sequence_episodes(table, scenes.get(scene_name), neighbours, crop, min_length)
                    parts[name] += [save_episode(dataset, episode, sequence) for episode in episodes]
                except Exception as error:
                    raise PartError(name, f"{type(error).__name__}: {error}") from error
                progress(f"{name}: {sequence} -> {len(episodes)} episodes")
        dataset.finalize()
    return parts


def save_episode(dataset, episode: dict[str, np.ndarray], task: str) -> int:
    """Add ``episode``'s frames to ``dataset`` as its next episode; return that episode's index."""
    for t in range(len(episode[TRAJECTORY_KEY])):
        dataset.add_frame({key: values[t] for key, values in episode.items()} | {"task": task})
    index = dataset.meta.total_episodes
    dataset.save_episode()
    return index


def data_config(
    root: Path,
    split: dict[str, list[int]],
    neighbours: NeighbourConfig,
    crop: CropConfig,
    episodes: list[int] | None = None,
) -> dict:
    """A fold's data config: the protocol's window geometry, the modalities and the episode split.

    ``episodes`` (default: the split's union) is the selection decoded into the window cache:
    configs that select the same episodes share one cache build. Every key is written (defaults
    included), so any of them can be overridden on the command line.
    """
    blocks = neighbours.count * neighbours.steps  # SLOT_DIM blocks per frame, one per neighbour step
    config = {
        "root": str(Path(root).resolve()),
        "repo_id": f"local/{Path(root).name}",
        "history": HISTORY,
        "horizon": HORIZON,
        "image_size": [crop.pixels, crop.pixels],
        "include_target_past": True,  # the constant-velocity reference of eval
        "episodes": episodes,
        "split": split,
        "modalities": {
            "trajectory": {"feature": TRAJECTORY_KEY, "planar": [[0, 1], [2, 3]]},
            "neighbours": {
                "feature": NEIGHBOURS_KEY,
                "encoder": "deepsets",
                "encoder_kwargs": {"slot_dim": neighbours.slot_dim},
                "raw_dims": list(range(SLOT_DIM - 1, blocks * SLOT_DIM, SLOT_DIM)),
                "planar": [[k * SLOT_DIM + d, k * SLOT_DIM + d + 1] for k in range(blocks) for d in (0, 2)],
            },
            # A heading-up crop turns with the agent, so it has no north to turn.
            "scene": {"feature": SCENE_KEY, "top_down": not crop.heading},
        },
        "target": {"feature": TRAJECTORY_KEY, "dims": [0, 1], "relative": True, "planar": [[0, 1]]},
    }
    return DataConfig.from_dict(config).to_dict()


def part_files(raw_dir: Path, folds: list[str]) -> dict[str, tuple[str, Path]]:
    """``{part: (sequence, file)}``: every file the ``folds`` read, once; a part is the file's stem
    (``biwi_eth_train``, ``biwi_eth_val``, ``biwi_eth`` for the whole file)."""
    parts = {}
    for fold in folds:
        for entries in fold_files(raw_dir, fold).values():
            parts.update({path.stem: (sequence, path) for sequence, path in entries})
    return parts


def fold_split(raw_dir: Path, fold: str, parts: dict[str, list[int]]) -> dict[str, list[int]]:
    """Fold ``fold``'s ``{split: episodes}`` from the episodes of each converted part."""
    return {
        name: sorted(e for _, path in entries for e in parts[path.stem])
        for name, entries in fold_files(raw_dir, fold).items()
    }


def shard_parts(rows: list[int], workers: int) -> list[range]:
    """Split parts of ``rows`` rows, in order, into at most ``workers`` contiguous non-empty ranges of
    about equal rows: each part goes to the shard its middle row falls in."""
    ends = np.cumsum(rows)
    middles = ends - np.asarray(rows) / 2
    shard_of = np.minimum((middles * workers / ends[-1]).astype(int), workers - 1)
    bounds = [0, *(np.flatnonzero(np.diff(shard_of)) + 1).tolist(), len(rows)]
    return [range(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _failure(parts: list[str], detail: str, files: dict[str, tuple[str, Path]]) -> ConversionError:
    named = ", ".join(f"{part} ({files[part][1]})" for part in parts)
    return ConversionError(f"converting ETH/UCY {named} failed: {detail}")


def _write_shards(
    roots: list[Path], shards: list[dict], raw_dir: Path, neighbours: NeighbourConfig, crop, files: dict
) -> list[dict[str, list[int]]]:
    """Write each shard into its root in a worker process of its own; their episodes per part, in
    order. The first failure stops them all and is raised as a `ConversionError` naming its part."""
    args = [(root, shard, raw_dir, neighbours, crop) for root, shard in zip(roots, shards, strict=True)]
    try:
        return run_shards(write_dataset, args, lambda _shard, line: logger.info("%s", line))
    except ShardError as failure:
        if isinstance(failure.error, PartError):
            raise _failure([failure.error.part], failure.error.detail, files) from None
        raise _failure(list(shards[failure.shard]), failure.detail, files) from None


def write_parts(
    work: Path,
    tables: dict[str, list[tuple[str, pd.DataFrame]]],
    files: dict[str, tuple[str, Path]],
    raw_dir: Path,
    neighbours: NeighbourConfig,
    crop: CropConfig,
    workers: int,
) -> tuple[Path, dict[str, list[int]]]:
    """Write the parts into one dataset under ``work``: in ``workers`` contiguous shards of about
    equal rows, one process each, joined in order by lerobot's `aggregate_datasets`. Return the
    dataset's path and its episodes per part, the same whatever ``workers`` is."""
    names = list(tables)
    ranges = shard_parts([sum(len(t) for _, t in tables[name]) for name in names], workers)
    shards = [{name: tables[name] for name in names[r.start : r.stop]} for r in ranges]
    dataset = work / DATASET_NAME
    if len(shards) == 1:  # no worker process: spares a second import of torch and lerobot
        try:
            return dataset, write_dataset(dataset, tables, raw_dir, neighbours, crop)
        except PartError as error:
            raise _failure([error.part], error.detail, files) from error
    roots = [work / f"shard-{k}" for k in range(len(shards))]
    written = _write_shards(roots, shards, raw_dir, neighbours, crop, files)
    counts = [sum(len(episodes) for episodes in shard.values()) for shard in written]
    offsets = np.cumsum([0, *counts[:-1]]).tolist()
    # A shard without an episode (only tracks too short) has nothing to add, nor the metadata to join.
    kept = [root for root, count in zip(roots, counts, strict=True) if count > 0]
    join_shards(kept, dataset, f"local/{DATASET_NAME}")
    parts = {}
    for shard, offset in zip(written, offsets, strict=True):
        parts |= {name: [offset + e for e in episodes] for name, episodes in shard.items()}
    return dataset, parts


def default_workers(rows: int) -> int:
    """One conversion process per `MIN_ROWS_PER_WORKER` of the input's ``rows``, at most one per core
    this process may run on; 1 (in this process) for a small input."""
    return max(1, min(len(os.sched_getaffinity(0)), rows // MIN_ROWS_PER_WORKER))


def convert(
    raw_dir: Path,
    folds: list[str],
    out: Path,
    neighbours: NeighbourConfig = NeighbourConfig(),
    crop: CropConfig = CropConfig(),
    workers: int | None = None,
) -> list[Path]:
    """Convert the files of ``folds`` once into ``out/ethucy/``; write each fold's data config to
    ``out/<fold>.yaml`` (returned), every config selecting all the dataset's episodes.

    ``workers`` processes (1: in this process; default: one per `MIN_ROWS_PER_WORKER` rows of the
    files, at most one per core, so a small input is converted in this process; never more than the
    files) write the files in contiguous shards; the dataset is the same whatever their number. It is
    built in a temp dir under ``out`` and renamed into place, so a failed or killed conversion
    leaves no ``out/ethucy`` (the next conversion removes what a killed one left).
    """
    out = Path(out)
    root = out / DATASET_NAME
    if root.exists():
        raise FileExistsError(f"{root} exists; remove it or choose another --out to convert ETH/UCY again")
    if workers is not None and workers < 1:
        raise ValueError(f"--workers {workers}: expected at least 1 conversion process")
    files = part_files(raw_dir, folds)  # checks every file before anything is written
    tables = {part: [(sequence, read_sequence(path))] for part, (sequence, path) in files.items()}
    rows = sum(len(table) for part in tables.values() for _, table in part)
    workers = min(workers or default_workers(rows), len(tables))
    with staging_dir(out, STAGING_PREFIX, "choose a writable --out") as work:
        dataset, parts = write_parts(work, tables, files, raw_dir, neighbours, crop, workers)
        os.rename(dataset, root)
    everything = sorted(e for episodes in parts.values() for e in episodes)
    paths = []
    for fold in folds:
        config = data_config(root, fold_split(raw_dir, fold, parts), neighbours, crop, everything)
        path = out / f"{fold}.yaml"
        header = (
            f"# ETH/UCY fold {fold!r} (test: {', '.join(FOLDS[fold])}) over the dataset {root}, "
            "written by `mmf-rl import ethucy`\n"
        )
        write_text_atomic(path, header + yaml.safe_dump(config, sort_keys=False, default_flow_style=None))
        paths.append(path)
    return paths


EXAMPLES = (
    "examples:\n"
    "  mmf-rl import ethucy ../shared/data/ethucy --out data/ethucy --fold eth "
    "&& mmf-rl train data=data/ethucy/eth.yaml\n"
    "  mmf-rl import ethucy ../shared/data/ethucy --out data/ethucy   # all five folds"
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mmf-rl import",
        description="convert a public dataset to LeRobot v3.0, with a data config to train on it",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EXAMPLES,
    )
    sources = parser.add_subparsers(dest="source", required=True)
    ethucy = sources.add_parser(
        "ethucy",
        help="ETH/UCY pedestrians: one dataset, a data config per leave-one-scene-out fold",
        description="ETH/UCY pedestrians -> OUT/ethucy/ (LeRobot v3.0, every file converted once) and "
        "OUT/<fold>.yaml per fold (data config: train with `mmf-rl train data=OUT/<fold>.yaml`)",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=EXAMPLES,
    )
    ethucy.add_argument("raw_dir", type=Path, help="the folder holding trajectories/ and scenes/")
    ethucy.add_argument("--out", type=Path, required=True, help="output folder")
    ethucy.add_argument(
        "--fold",
        choices=sorted(FOLDS),
        action="append",
        help="a fold (repeatable; default all): converts only the files it reads",
    )
    ethucy.add_argument("--neighbours", type=int, default=8, help="K nearest agents per step")
    ethucy.add_argument(
        "--neighbour-steps",
        type=int,
        default=1,
        help="steps of each neighbour's own track per slot (1: the frame only)",
    )
    ethucy.add_argument("--crop-pixels", type=int, default=64, help="scene crop side in pixels")
    ethucy.add_argument("--crop-metres", type=float, default=8.0, help="scene crop side in metres")
    ethucy.add_argument(
        "--crop-heading", action="store_true", help="crop with the agent's heading up (default north up)"
    )
    ethucy.add_argument(
        "--workers",
        type=int,
        help="conversion processes, each writing a contiguous share of the files (default: one per "
        f"{MIN_ROWS_PER_WORKER} rows of the files, at most one per core; never more than the files; 1: "
        "no extra process); the dataset is the same for any number",
    )
    return parser


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    crop = CropConfig(args.crop_pixels, args.crop_metres, args.crop_heading)
    try:
        folds = args.fold or sorted(FOLDS)
        neighbours = NeighbourConfig(args.neighbours, args.neighbour_steps)
        paths = convert(args.raw_dir, folds, args.out, neighbours, crop, args.workers)
        for path in paths:
            logger.info("fold %s: train with `mmf-rl train data=%s`", path.stem, path)
    except (OSError, ValueError, ConversionError) as error:
        return report_command_error("mmf-rl import ethucy", error)
    return 0
