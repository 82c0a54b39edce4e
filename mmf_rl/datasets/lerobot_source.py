"""Reading a LeRobot v3.0 dataset through lerobot's own metadata, parquet and video utilities.

Only what lerobot does not provide lives here: mapping features to modalities, selecting
episodes, finding which video files exist, and decoding whole episodes (resized, uint8) straight
into the window cache, from videos (``dtype: video``) or from images stored in the parquet files
(``dtype: image``, what ``LeRobotDataset.create(use_videos=False)`` writes).
lerobot is imported lazily: importing it costs seconds, and spawned decode workers only need
its video utilities.
"""

from __future__ import annotations

import copy
import functools
import itertools
import json
import os
import shlex
import stat
import time
import warnings
from dataclasses import dataclass
from importlib.metadata import version as package_version
from pathlib import Path, PurePosixPath

import numpy as np
import packaging.version
import pyarrow as pa
import pyarrow.parquet as pq

from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.splits import select_episodes
from mmf_rl.keys import ModalitySpec, obs_key

# Bytes of decoded frames per decode call: lerobot returns float32 frames at full resolution,
# so a call covers many small frames (fast) but only a few HD ones (bounded memory).
DECODE_CHUNK_BYTES = 64 * 2**20

INFO_FILE = Path("meta") / "info.json"
# The info.json keys the pipeline reads; `video_path` too when a feature is a video.
REQUIRED_INFO_KEYS = ("codebase_version", "features", "total_frames")
# Per-frame bookkeeping columns every LeRobot dataset has; the pipeline reads the first three.
FRAME_COLUMNS = ("index", "episode_index", "timestamp")
BOOKKEEPING_FEATURES = (*FRAME_COLUMNS, "frame_index", "task_index")
# lerobot's v2.1 -> v3.0 converter (in lerobot 0.4.4 the only one it ships).
V21_CONVERTER = "lerobot.datasets.v30.convert_dataset_v21_to_v30"
# The path templates info.json may hold; each must stay inside the dataset root.
PATH_TEMPLATE_KEYS = ("data_path", "video_path")
DEFAULT_TEMPLATES = {
    "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
    "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
}
# Declared sizes beyond these are refused before anything is allocated from them: a frame of more
# than 2^28 values (16k x 16k RGB), a vector feature of more than 2^16 dims.
MAX_FRAME_VALUES = 2**28
MAX_VECTOR_WIDTH = 2**16
# What a damaged or unreadable camera file raises while decoding: torchcodec's and torchvision's
# decoders (RuntimeError from FFmpeg or libpng/libjpeg, ValueError for a file without a video
# stream, IndexError for a frame past the end), lerobot's FrameTimestampError (a ValueError) and
# OSError for a missing or unreadable file. Anything else (a TypeError from an API change) is a
# bug and propagates instead of being cached as "camera absent".
DECODE_ERRORS = (RuntimeError, ValueError, IndexError, OSError)
# The undecodable images of a camera that a cache report names (the first ones, with their errors);
# the others are only marked absent.
REPORTED_IMAGE_ERRORS = 10


@dataclass(frozen=True)
class ResolvedModality:
    """A modality after checking its config against the dataset's features."""

    spec: ModalitySpec
    feature: str
    dims: list[int] | None
    valid_feature: str | None
    storage: str  # "video" (mp4 files), "image" (encoded images in the parquet files) or "vector"

    @property
    def is_video(self) -> bool:
        return self.storage == "video"

    @property
    def is_camera(self) -> bool:
        return self.storage in ("video", "image")


@dataclass(frozen=True)
class Episode:
    index: int
    start: int  # its first row in the window cache (the global frame index when every episode is selected)
    stop: int  # one past its last row
    first_frame: int  # the global frame index of its first frame


def open_metadata(config: DataConfig):
    """``LeRobotDatasetMetadata`` for the config's dataset (see :func:`open_dataset_metadata`)."""
    return open_dataset_metadata(config.root, config.repo_id)


def open_dataset_metadata(root: str | Path | None, repo_id: str):
    """``LeRobotDatasetMetadata`` for a local ``root`` (never downloads) or the hub ``repo_id``.

    A local dataset is checked first (layout, info.json, format version, parquet footers) so a
    problem is reported by file instead of as a traceback from deep inside lerobot or pyarrow,
    and so lerobot never falls back to downloading into ``root`` when a metadata file is absent.
    """
    if root is None:
        from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

        meta = LeRobotDatasetMetadata(repo_id)
        # The hub path: fetch data and videos the way lerobot does; absent videos stay absent.
        meta.pull_from_repo(allow_patterns=["data/*", "videos/*"])
        return meta
    root = Path(root)
    _check_local_dataset(root)
    fingerprint = _meta_fingerprint(root)
    if time.time_ns() - max(mtime for *_, mtime in fingerprint) < META_MEMO_SETTLED_NS:
        return _read_metadata(root, repo_id)
    # A copy each: no caller changes what the next one gets.
    meta = copy.deepcopy(_settled_metadata(root.resolve(), repo_id, fingerprint))
    meta.root = root
    return meta


def _read_metadata(root: Path, repo_id: str):
    """lerobot's ``LeRobotDatasetMetadata`` of the checked local dataset at ``root``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    try:
        return LeRobotDatasetMetadata(repo_id, root=root)
    except Exception as error:  # noqa: BLE001 - whatever lerobot trips on, report it by directory
        raise ValueError(
            f"{root / 'meta'}: lerobot {package_version('lerobot')} could not read the dataset metadata "
            f"({_one_line(error)}); restore meta/ from the original dataset or re-record it"
        ) from None


# lerobot re-reads and re-validates every meta/ parquet file (through `datasets`) on each construction,
# 0.15-0.4 s, and a run or a study opens the same dataset many times. The memo is keyed by meta/'s
# fingerprint too, so any change on disk reloads; failures are never stored (lru_cache keeps no
# exception). A fingerprint is trusted only once meta/'s files are older than META_MEMO_SETTLED_NS: a
# file rewritten within one filesystem timestamp tick keeps its size and mtime.
META_MEMO_SIZE = 8
META_MEMO_SETTLED_NS = 2 * 10**9


@functools.lru_cache(maxsize=META_MEMO_SIZE)
def _settled_metadata(root: Path, repo_id: str, fingerprint: tuple) -> object:
    """`_read_metadata`, remembered per ``(root, repo_id, fingerprint)`` (the fingerprint: only the key)."""
    return _read_metadata(root, repo_id)


def _meta_fingerprint(root: Path) -> tuple[tuple[str, int, int], ...]:
    """(relative path, size, mtime_ns) of every file under ``root/meta``, sorted."""
    meta = root / "meta"
    found = []
    for path in meta.rglob("*"):
        try:
            info = path.stat()
        except FileNotFoundError:  # removed meanwhile: the fingerprint is of what is left
            continue
        if stat.S_ISREG(info.st_mode):
            found.append((path.relative_to(meta).as_posix(), info.st_size, info.st_mtime_ns))
    return tuple(sorted(found))


def _one_line(error: BaseException) -> str:
    """``Type: message`` on one line, from the innermost cause (wrappers like ``datasets``' say little)."""
    while (error.__cause__ or error.__context__) is not None:
        error = error.__cause__ or error.__context__
    return f"{type(error).__name__}: {' '.join(str(error).split())}"[:400]


def _check_local_dataset(root: Path) -> None:
    """Raise a clear error unless ``root`` holds a LeRobot v3.0 dataset lerobot can open."""
    if not root.exists():
        raise FileNotFoundError(
            f"dataset root {root} does not exist: set `root` to the directory of a LeRobot v3.0 dataset "
            "(the one holding meta/info.json, data/ and videos/), or leave `root` unset to read `repo_id` "
            "from the Hugging Face hub"
        )
    if not root.is_dir():
        raise NotADirectoryError(
            f"dataset root {root} is a file, not a directory: set `root` to a dataset directory"
        )
    info_path = root / INFO_FILE
    if not info_path.is_file():
        found = sorted(p.name + ("/" if p.is_dir() else "") for p in root.iterdir())
        nested = sorted(p.parent.parent for p in root.glob(f"*/{INFO_FILE}"))
        hint = f"; did you mean `root: {nested[0]}`?" if nested else ""
        raise FileNotFoundError(
            f"{root} is not a LeRobot dataset: {info_path} does not exist (found "
            f"{found[:10] + ['...'] if len(found) > 10 else found or 'an empty directory'}); "
            f"set `root` to the directory holding meta/, data/ and videos/{hint}"
        )
    info = _read_info(root)
    _check_version(root, info)
    _check_info(info_path, info)
    tasks = root / "meta" / "tasks.parquet"
    episodes = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not tasks.is_file() or not episodes:
        absent = [str(tasks)] if not tasks.is_file() else []
        absent += [] if episodes else [f"{root / 'meta' / 'episodes'}/chunk-*/file-*.parquet"]
        raise FileNotFoundError(
            f"{root} is an incomplete LeRobot v3.0 dataset: {', '.join(absent)} missing; "
            "restore meta/ from the original dataset or re-record it"
        )
    for path in [tasks, *episodes]:
        _read_parquet_schema(path)


def _read_info(root: Path) -> dict:
    path = root / INFO_FILE
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: not valid JSON ({error}); restore it from the original dataset") from None
    if not isinstance(info, dict):
        raise ValueError(f"{path}: expected a JSON object, found {type(info).__name__}")
    return info


def _check_version(root: Path, info: dict) -> None:
    """Reject v2.x (and older) datasets with lerobot's converter command, and newer majors."""
    from lerobot.datasets.lerobot_dataset import CODEBASE_VERSION

    path = root / INFO_FILE
    found = info.get("codebase_version")
    try:
        version = packaging.version.parse(str(found))
    except packaging.version.InvalidVersion:
        raise ValueError(
            f"{path}: `codebase_version` should be a version like {CODEBASE_VERSION!r}, found {found!r}"
        ) from None
    supported = packaging.version.parse(CODEBASE_VERSION)
    # A v2 layout keeps its episodes in meta/episodes.jsonl (v3.0: meta/episodes/*/*.parquet).
    v2_layout = (root / "meta" / "episodes.jsonl").is_file() and not (root / "meta" / "episodes").is_dir()
    if version.major < supported.major or v2_layout:
        command = (
            f"python -m {V21_CONVERTER} --repo-id={shlex.quote(root.name)} "
            f"--root={shlex.quote(str(root.parent))} --push-to-hub=false"
        )
        older = (
            ""
            if version >= packaging.version.parse("v2.1")
            else f" That converter takes only v2.1: first bring this {found} dataset to v2.1 with the "
            "convert_dataset_v20_to_v21 script of an older lerobot release, then run it."
        )
        raise ValueError(
            f"{root} is a LeRobot v2.x dataset ({path}: codebase_version {found!r}"
            f"{', but the v2 layout meta/episodes.jsonl' if v2_layout else ''}); "
            f"lerobot {package_version('lerobot')} and mmf-rl read only {CODEBASE_VERSION}. Convert it in "
            "place with lerobot's converter (the original "
            f"is kept as {root.parent / (root.name + '_old')}).{older}\n  {command}"
        )
    if version.major > supported.major:
        raise ValueError(
            f"{path}: codebase_version {found!r} is newer than the {CODEBASE_VERSION} that lerobot "
            f"{package_version('lerobot')} reads; upgrade lerobot (and mmf-rl) to read it"
        )


def _check_info(path: Path, info: dict) -> None:
    missing = [key for key in REQUIRED_INFO_KEYS if key not in info]
    if missing:
        raise ValueError(
            f"{path}: missing key(s) {missing}; a LeRobot v3.0 info.json has {list(REQUIRED_INFO_KEYS)}. "
            "Restore it from the original dataset or re-record it"
        )
    _check_path_templates(path, info)
    total = info["total_frames"]
    if not isinstance(total, int) or isinstance(total, bool) or total < 0:
        raise ValueError(f"{path}: `total_frames` should be a non-negative integer, found {total!r}")
    features = info["features"]
    if not isinstance(features, dict) or not features:
        raise ValueError(
            f"{path}: `features` should map feature names to {{dtype, shape, names}}, found {features!r}"
        )
    for name, ft in features.items():
        _check_feature(path, name, ft)
    absent = [c for c in FRAME_COLUMNS if c not in features]
    if absent:
        raise ValueError(
            f"{path}: `features` lacks the per-frame column(s) {absent} every LeRobot dataset has"
        )
    if any(ft["dtype"] == "video" for ft in features.values()) and not info.get("video_path"):
        raise ValueError(f"{path}: the dataset has video features but no `video_path` pattern")


def _check_path_templates(path: Path, info: dict) -> None:
    """A dataset from the hub is untrusted input: its path templates must not lead out of the root."""
    for key in PATH_TEMPLATE_KEYS:
        template = info.get(key)
        if template is None:
            continue
        parts = PurePosixPath(str(template)).parts
        if (
            not isinstance(template, str)
            or PurePosixPath(template).is_absolute()
            or ".." in parts
            or "\\" in template
        ):
            raise ValueError(
                f"{path}: `{key}` {template!r} leads outside the dataset root; a LeRobot path template is "
                f"relative to the root without '..' (like {DEFAULT_TEMPLATES[key]!r}). Restore info.json "
                "from the original dataset"
            )


def _check_feature(path: Path, name: str, ft) -> None:
    """One entry of ``features``: a dtype and a plausible shape for its kind."""
    if not isinstance(ft, dict) or "dtype" not in ft or "shape" not in ft:
        found = sorted(ft) if isinstance(ft, dict) else repr(ft)
        raise ValueError(f"{path}: feature {name!r} needs `dtype` and `shape`, found {found}")
    shape = ft["shape"]
    if (
        not isinstance(shape, list)
        or not shape
        or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 1 for s in shape)
    ):
        raise ValueError(
            f"{path}: feature {name!r} `shape` should be a list of positive integers, found {shape!r}"
        )
    if ft["dtype"] == "video" and len(shape) != 3:
        raise ValueError(
            f"{path}: video feature {name!r} `shape` should be [height, width, channels], found {shape}"
        )
    if int(np.prod(shape, dtype=object)) > MAX_FRAME_VALUES:
        raise ValueError(
            f"{path}: feature {name!r} declares `shape` {shape}, "
            f"{int(np.prod(shape, dtype=object)):.3g} values "
            f"per frame (more than {MAX_FRAME_VALUES}); this is not a real sensor. Restore info.json "
            "from the original dataset"
        )
    if ft["dtype"] == "image" and len(shape) not in (2, 3):
        raise ValueError(
            f"{path}: image feature {name!r} `shape` should be [height, width, channels] or [height, "
            f"width], found {shape}"
        )


def _read_parquet_schema(path: Path) -> pa.Schema:
    """The schema in a parquet file's footer: reading it proves the file is not truncated."""
    try:
        return pq.read_schema(path)
    except (pa.ArrowException, OSError) as error:
        raise _unreadable_parquet(path, error) from None


def _unreadable_parquet(path: Path, error: BaseException) -> ValueError:
    return ValueError(
        f"{path}: not a readable parquet file ({path.stat().st_size} bytes; {_one_line(error)}). It is "
        "probably truncated or corrupted (an interrupted copy, download or recording): restore it from "
        "the original dataset"
    )


def _is_numeric(dtype: str) -> bool:
    try:
        return np.dtype(dtype).kind in "biuf"
    except TypeError:  # lerobot's "video", "image", "string"
        return False


def _arrow_layout(arrow_type: pa.DataType) -> tuple[pa.DataType, int | None, bool]:
    """A column's (value type, values per frame if fixed, whether it is a list)."""
    if pa.types.is_fixed_size_list(arrow_type):
        return arrow_type.value_type, arrow_type.list_size, True
    if pa.types.is_list(arrow_type) or pa.types.is_large_list(arrow_type):
        return arrow_type.value_type, None, True
    return arrow_type, 1, False


def _check_stored_column(path: Path, schema: pa.Schema, column: str, ft: dict, info_path: Path) -> None:
    """Data file ``path`` has ``column`` and, for a numeric feature, stores it as info.json's
    ``ft`` declares (a scalar for shape ``[1]``, a list of that length for a vector)."""
    declared = f"dtype {ft['dtype']!r} shape {list(ft['shape'])}"
    if column not in schema.names:
        raise ValueError(
            f"{path}: no column {column!r}, which {info_path} declares ({declared}); found "
            f"columns {schema.names}. Restore the data file, or fix `features` in info.json"
        )
    if not _is_numeric(ft["dtype"]):
        return
    arrow_type = schema.field(column).type
    value_type, per_frame, is_list = _arrow_layout(arrow_type)
    shape = tuple(ft["shape"])
    if shape == (1,):  # lerobot stores a shape-[1] feature as a scalar column
        fits_shape = not is_list
    elif len(shape) == 1:
        fits_shape = is_list and per_frame in (None, shape[0])
    else:  # arrays: never read by the pipeline, left to lerobot
        fits_shape = True
    numeric = any(
        check(value_type) for check in (pa.types.is_integer, pa.types.is_floating, pa.types.is_boolean)
    )
    if not fits_shape or not numeric:
        found = f"{per_frame} value(s) per frame" if per_frame is not None else "a variable-length list"
        raise ValueError(
            f"{path}: column {column!r} holds {arrow_type} ({found}), but {info_path} declares "
            f"{declared}; fix the feature's `shape`/`dtype` in info.json to match the data, or "
            "restore the data file"
        )


def _validity_candidates(feature: str) -> list[str]:
    """Validity feature names looked up when the config names none.

    ``<feature>_valid``, and for a camera ``observation.images.<cam>`` also
    ``observation.<cam>_camera_valid`` (the recorder's name: lerobot 0.4.4 treats any feature
    whose name contains "image" as a camera when aggregating stats, so a flag cannot use it).
    """
    candidates = [f"{feature}_valid"]
    camera_prefix = "observation.images."
    if feature.startswith(camera_prefix):
        candidates.append(f"observation.{feature.removeprefix(camera_prefix)}_camera_valid")
    return candidates


def _camera_channels(feature: str, ft: dict, info_path: Path) -> int:
    """Channels of a camera feature: 3 (colour) or 1 (grey, depth). ``shape`` is ``[h, w, c]`` unless
    ``names`` puts ``channels`` elsewhere; a 2-D ``[h, w]`` image has one channel."""
    shape = list(ft["shape"])
    if len(shape) == 2:
        return 1
    names = ft.get("names") or ["height", "width", "channels"]
    channels = int(shape[names.index("channels")]) if "channels" in names else int(shape[-1])
    if channels not in (1, 3):
        raise ValueError(
            f"{info_path}: camera feature {feature!r} has {channels} channels (shape {shape}, names "
            f"{names}); "
            "mmf-rl reads colour (3) or single-channel (1, e.g. depth) cameras"
        )
    return channels


def _check_dims(dims: list[int] | None, width: int, what: str) -> None:
    if dims is not None and (not dims or min(dims) < 0 or max(dims) >= width):
        raise ValueError(
            f"{what}: dims {dims} out of range for a feature of width {width} (valid: 0..{width - 1})"
        )


class LeRobotSource:
    """A LeRobot dataset seen through a :class:`DataConfig`: modalities resolved, files located."""

    def __init__(self, config: DataConfig):
        self.config = config
        self.meta = open_metadata(config)
        self.root = Path(self.meta.root)
        self.features: dict[str, dict] = self.meta.features
        self.modalities = {name: self._resolve(name) for name, _ in sorted(config.modalities.items())}
        self.target_feature, self.target_dim = self._resolve_vector(
            config.target.feature, config.target.dims, "target"
        )
        self.reference_feature = self._resolve_reference(config.target)
        self.action_feature, self.action_dim = None, None
        if config.action is not None:
            self.action_feature, self.action_dim = self._resolve_vector(
                config.action.feature, config.action.dims, "action"
            )
        # As meta/episodes declares them (start/stop: global frame indices), checked before any use.
        declared = [
            Episode(
                int(e["episode_index"]),
                int(e["dataset_from_index"]),
                int(e["dataset_to_index"]),
                int(e["dataset_from_index"]),
            )
            for e in self.meta.episodes
        ]
        self._check_data_files()
        self._check_episode_ranges(declared)
        selected = set(select_episodes([e.index for e in declared], config, self.root))
        self.selected_all = len(selected) == len(declared)
        self.episodes, row = [], 0
        for episode in sorted(declared, key=lambda e: e.start):  # cache rows follow the global frame index
            if episode.index in selected:
                self.episodes.append(
                    Episode(episode.index, row, row + episode.stop - episode.start, episode.start)
                )
                row += episode.stop - episode.start
        self._check_window_fits()

    @property
    def specs(self) -> list[ModalitySpec]:
        return [m.spec for m in self.modalities.values()]

    def _require_feature(self, feature: str, what: str) -> str:
        if feature not in self.features:
            raise ValueError(
                f"{what}: feature {feature!r} is not in the dataset at {self.root} (meta/info.json); "
                f"available features: {sorted(self.features)}"
            )
        return feature

    def _vector_width(self, feature: str, what: str) -> int:
        ft = self.features[feature]
        if not _is_numeric(ft["dtype"]) or len(ft["shape"]) != 1:
            vectors = sorted(
                name
                for name, f in self.features.items()
                if _is_numeric(f["dtype"]) and len(f["shape"]) == 1 and name not in BOOKKEEPING_FEATURES
            )
            raise ValueError(
                f"{what}: feature {feature!r} has dtype {ft['dtype']!r} and shape {list(ft['shape'])} "
                f"({self.root / INFO_FILE}), but it must be a numeric vector (a float, int or bool dtype, "
                f"shape [d]); use one of the dataset's numeric vector features: {vectors}"
            )
        if ft["shape"][0] > MAX_VECTOR_WIDTH:
            raise ValueError(
                f"{what}: feature {feature!r} declares `shape` {list(ft['shape'])} in "
                f"{self.root / INFO_FILE}, "
                f"more than {MAX_VECTOR_WIDTH} dims; a model input that wide is not a sensor. Fix info.json, "
                "or select the dims to use (`dims`)"
            )
        return int(ft["shape"][0])

    def _resolve_vector(self, feature: str, dims: list[int] | None, what: str) -> tuple[str, int]:
        """A numeric vector feature (the target, the action) and its width after ``dims``."""
        self._require_feature(feature, what)
        width = self._vector_width(feature, what)
        _check_dims(dims, width, f"{what} {feature!r}")
        return feature, len(dims) if dims is not None else width

    def _resolve_reference(self, target) -> str | None:
        """``target.relative_to``'s feature, checked to give one value per target dim."""
        reference = target.relative_to
        if reference is None:
            return None
        feature, width = self._resolve_vector(reference.feature, reference.dims, "target.relative_to")
        if width != self.target_dim:
            raise ValueError(
                f"target.relative_to: {reference.feature!r} dims {reference.dims} give {width} values, the "
                f"target ({target.feature!r} dims {target.dims}) has {self.target_dim}; give one reference "
                "dim per target dim, in the target's order (e.g. the gripper's x, y for the object's x, y)"
            )
        return feature

    def _episodes_file(self, position: int) -> Path:
        """The meta/episodes parquet file that lists the episode at ``position`` of ``meta.episodes``."""
        from lerobot.datasets.utils import DEFAULT_EPISODES_PATH

        row = self.meta.episodes[position]
        return self.root / DEFAULT_EPISODES_PATH.format(
            chunk_index=int(row["meta/episodes/chunk_index"]), file_index=int(row["meta/episodes/file_index"])
        )

    def _check_episode_ranges(self, episodes: list[Episode]) -> None:
        """Every declared episode's ``[dataset_from_index, dataset_to_index)`` lies in the data's frames,
        and no two overlap: each frame belongs to at most one episode (checked before anything is indexed)."""
        total = self.meta.total_frames
        for position, episode in enumerate(episodes):
            if not 0 <= episode.start <= episode.stop <= total:
                raise ValueError(
                    f"{self._episodes_file(position)}: episode {episode.index} has dataset_from_index="
                    f"{episode.start}, dataset_to_index={episode.stop}; expected 0 <= from <= to <= {total} "
                    f"(total_frames in {self.root / INFO_FILE}). Restore meta/episodes from the original "
                    "dataset"
                )
        ordered = sorted(range(len(episodes)), key=lambda i: episodes[i].start)
        for before, after in itertools.pairwise(ordered):
            a, b = episodes[before], episodes[after]
            if b.start < a.stop:
                raise ValueError(
                    f"{self._episodes_file(after)}: episode {b.index} (frames {b.start}..{b.stop - 1}, "
                    f"dataset_from_index/dataset_to_index) overlaps episode {a.index} (frames {a.start}.."
                    f"{a.stop - 1}); each frame belongs to one episode. Restore meta/episodes from the "
                    "original dataset"
                )

    def _check_window_fits(self) -> None:
        """At least one episode must hold one window, or the dataset would give no sample at all."""
        config = self.config
        needed = (config.history + config.horizon - 1) * config.stride + 1
        if not self.episodes:
            raise ValueError(
                f"{self.root}: the dataset has no episodes (meta/episodes lists none); record some"
            )
        longest = max(self.episodes, key=lambda e: e.stop - e.start)
        if longest.stop - longest.start < needed:
            raise ValueError(
                f"{self.root}: every episode is shorter than one window. A window of "
                f"history={config.history} "
                f"and horizon={config.horizon} at stride={config.stride} spans "
                f"(history + horizon - 1) * stride + 1 = {needed} frames, but the longest episode "
                f"(episode {longest.index}) has {longest.stop - longest.start} frames. Lower `history`, "
                f"`horizon` or `stride` so that the window fits"
            )

    def _columns(self) -> set[str]:
        """The per-frame parquet columns the pipeline reads."""
        columns = {*FRAME_COLUMNS, self.target_feature}
        if self.reference_feature is not None:
            columns.add(self.reference_feature)
        if self.action_feature is not None:
            columns.add(self.action_feature)
        for m in self.modalities.values():
            if not m.is_camera:
                columns.add(m.feature)
            if m.valid_feature is not None:
                columns.add(m.valid_feature)
        return columns

    def _check_data_files(self) -> None:
        """Every data file is readable and stores its columns as info.json declares.

        Only the parquet footers are read, so this costs milliseconds per file; without it a
        mismatch surfaces as a cast error deep inside ``datasets``, naming no file.
        """
        paths = sorted((self.root / "data").glob("*/*.parquet"))
        if not paths:
            raise FileNotFoundError(
                f"{self.root} has no data files: expected {self.root / 'data'}/chunk-*/file-*.parquet; "
                "restore data/ from the original dataset"
            )
        info_path = self.root / INFO_FILE
        # lerobot casts every declared non-video feature when it loads the data, used or not.
        stored = sorted(name for name, ft in self.features.items() if ft["dtype"] != "video")
        rows = 0
        for path in paths:
            schema = _read_parquet_schema(path)
            rows += pq.read_metadata(path).num_rows
            for column in stored:
                _check_stored_column(path, schema, column, self.features[column], info_path)
        if rows != self.meta.total_frames:
            raise ValueError(
                f"{info_path}: `total_frames` is {self.meta.total_frames}, but the data files hold {rows} "
                f"frames ({len(paths)} file(s) under {self.root / 'data'}); fix total_frames, or restore "
                "the data files"
            )

    def _resolve(self, name: str) -> ResolvedModality:
        cfg = self.config.modalities[name]
        what = f"modality {name!r}"
        feature = self._require_feature(cfg.feature, what)
        ft = self.features[feature]
        if ft["dtype"] in ("video", "image"):
            if cfg.kind not in (None, "image"):
                raise ValueError(
                    f"{what}: feature {feature!r} is a camera ({ft['dtype']}), so kind must be 'image', "
                    f"found {cfg.kind!r}"
                )
            shape = (_camera_channels(feature, ft, self.root / INFO_FILE), *self.config.image_size)
            kind, dims, storage = "image", None, ft["dtype"]
        else:
            width = self._vector_width(feature, what)
            _check_dims(cfg.dims, width, f"{what} ({feature!r})")
            kind = cfg.kind or "sequence"
            if kind == "image":
                raise ValueError(f"{what}: feature {feature!r} is a vector, so kind cannot be 'image'")
            dims, storage = cfg.dims, "vector"
            shape = (len(dims) if dims is not None else width,)
        valid = cfg.valid_feature
        if valid is not None:
            self._require_feature(valid, f"{what} valid_feature")
        else:
            valid = next((c for c in _validity_candidates(feature) if c in self.features), None)
        spec = ModalitySpec(
            name=name,
            kind=kind,
            shape=shape,
            encoder=cfg.encoder,
            encoder_kwargs=dict(cfg.encoder_kwargs or {}),
            required=cfg.required,
        )
        return ResolvedModality(spec=spec, feature=feature, dims=dims, valid_feature=valid, storage=storage)

    def video_path(self, episode: int, feature: str) -> Path:
        path = self.root / self.meta.get_video_file_path(episode, feature)
        # The template was checked; the feature name it holds ({video_key}) is checked here.
        if os.path.commonpath([os.path.normpath(path), os.path.normpath(self.root)]) != os.path.normpath(
            self.root
        ):
            raise ValueError(
                f"{self.root / INFO_FILE}: the video of feature {feature!r} (episode {episode}) resolves "
                f"to {os.path.normpath(path)}, outside the dataset root; rename the feature"
            )
        return path

    def data_file(self, episode: int) -> Path:
        return self.root / self.meta.get_data_file_path(episode)

    def drop_episodes_with_unordered_timestamps(self, columns: dict[str, np.ndarray]) -> list[int]:
        """Skip (with a warning naming file and field) every episode whose ``timestamp`` does not
        increase frame after frame: its frames cannot be matched to video frames. Returns their indices."""
        kept, dropped = [], []
        for episode in self.episodes:
            steps = np.diff(columns["timestamp"][episode.start : episode.stop].astype(np.float64))
            if (steps > 0).all():
                kept.append(episode)
                continue
            frame = int(np.flatnonzero(steps <= 0)[0]) + 1
            stamps = columns["timestamp"][episode.start + frame - 1 : episode.start + frame + 1].tolist()
            warnings.warn(
                f"{self.data_file(episode.index)}: `timestamp` of episode {episode.index} does not "
                "increase at frame "
                f"{frame} ({stamps[0]} then {stamps[1]}); the episode is skipped (no window uses it)",
                stacklevel=2,
            )
            dropped.append(episode.index)
        self.episodes = kept
        return dropped

    def video_from_timestamp(self, episode: int, feature: str) -> float:
        return float(self.meta.episodes[episode][f"videos/{feature}/from_timestamp"])

    def missing_videos(self) -> dict[str, list[Path]]:
        """Per video modality, the files the metadata declares that are not on disk."""
        missing = {}
        for name, m in self.modalities.items():
            if m.is_video:
                paths = sorted({self.video_path(e.index, m.feature) for e in self.episodes})
                absent = [p for p in paths if not p.is_file()]
                if absent:
                    missing[name] = absent
        return missing

    def read_columns(self) -> dict[str, np.ndarray]:
        """The per-frame columns the pipeline needs, rows in cache order (selected episodes by frame
        ``index``).

        Keeps the dataset open for :meth:`image_column` if a camera is stored as images (otherwise
        its memory-mapped pages that the read touched would stay resident for the whole build).
        """
        selection = None if self.selected_all else self.episodes
        data, hf, row_order = load_frame_columns(self.meta, self._columns(), selection)
        if any(m.storage == "image" for m in self.modalities.values()):
            self._hf, self._row_order = hf, row_order
        return data

    def image_column(self, name: str):
        """Camera ``name``'s encoded images (``{"bytes", "path"}`` entries) as a one-column Hugging Face
        dataset, and the positions of its rows in cache row order (after :meth:`read_columns`).

        The dataset is memory-mapped, so it pickles as its file's path: decode workers receive it
        cheaply and read only their own rows.
        """
        feature = self.modalities[name].feature
        return self._hf.select_columns([feature]), self._row_order

    def files(self) -> list[Path]:
        """Every file that makes up the dataset: what the cache fingerprint covers."""
        return sorted(
            p for sub in ("meta", "data", "videos") for p in (self.root / sub).rglob("*") if p.is_file()
        )


def load_frame_data(meta, episodes: list[int] | None = None):
    """The frames of ``episodes`` (all when ``None``) of the dataset ``meta`` describes, through lerobot's
    loader (a memory-mapped Hugging Face dataset), with image features left encoded."""
    import datasets
    from lerobot.datasets.utils import get_hf_features_from_features, load_nested_dataset

    features = get_hf_features_from_features(meta.features)
    for name, ft in meta.features.items():
        if ft["dtype"] == "image":  # decoded later, in chunks, straight into the cache (not by PIL, per row)
            features[name] = datasets.Image(decode=False)
    return load_nested_dataset(Path(meta.root) / "data", features=features, episodes=episodes)


def load_frame_columns(meta, columns, episodes: list[Episode] | None = None):
    """Per-frame ``columns`` (plus ``index``) of ``episodes`` (all when ``None``) of the dataset ``meta``
    describes, read through lerobot's loader and ordered by the global frame ``index``; checked
    against the frames the metadata declares. Returns the columns, the loaded dataset and the row
    order that sorts it (to read more columns of the same rows later)."""
    root = Path(meta.root)
    try:
        hf = load_frame_data(meta, None if episodes is None else [e.index for e in episodes])
        table = hf.select_columns(sorted({*columns, "index"})).with_format("arrow")[:]
        order = np.argsort(_numpy_column(table.column("index")), kind="stable")
        # One column at a time: the memory-mapped table's pages are copied once, in frame order.
        data = {name: _numpy_column(table.column(name))[order] for name in table.column_names}
    except Exception as error:  # noqa: BLE001 - footers and schemas were fine: a damaged page or a cast
        raise _data_error(root, error) from None
    if episodes is None:
        expected = np.arange(meta.total_frames)
        declared = f"meta/info.json total_frames={len(expected)}"
    else:
        expected = np.concatenate(
            [np.arange(e.first_frame, e.first_frame + e.stop - e.start) for e in episodes]
        )
        declared = f"meta/episodes of the selected episodes {[e.index for e in episodes]}"
    if len(data["index"]) != len(expected) or not np.array_equal(data["index"], expected):
        raise ValueError(
            f"{root / 'data'}: frame `index` column should hold {len(expected)} frames "
            f"{expected[0] if len(expected) else None}..{expected[-1] if len(expected) else None} "
            f"({declared}), found {len(data['index'])} rows "
            f"from {data['index'].min() if len(data['index']) else None} to "
            f"{data['index'].max() if len(data['index']) else None}"
        )
    return data, hf, order


def _numpy_column(column: pa.ChunkedArray) -> np.ndarray:
    """An arrow column as numpy, a list column as ``[n, d]``: without the per-row arrays that
    ``datasets``' numpy formatter builds for a list column (an object per frame)."""
    array = column.combine_chunks()
    if _arrow_layout(array.type)[2]:  # a list column
        return array.flatten().to_numpy(zero_copy_only=False).reshape(len(array), -1)
    return array.to_numpy(zero_copy_only=False)


def read_frame_columns(meta, columns) -> dict[str, np.ndarray]:
    """Per-frame ``columns`` of the whole dataset ``meta`` describes.

    Ordered by the global frame ``index``.
    """
    return load_frame_columns(meta, columns)[0]


def _data_error(root: Path, error: BaseException) -> ValueError:
    """The error for data that failed to load: names the file that fails on its own, if one does."""
    for path in sorted((root / "data").glob("*/*.parquet")):
        try:
            pq.read_table(path)
        except (pa.ArrowException, OSError) as file_error:
            return _unreadable_parquet(path, file_error)
    return ValueError(
        f"{root / 'data'}: the parquet files do not hold what {root / INFO_FILE} declares "
        f"({_one_line(error)}); fix the features' `dtype`/`shape` in info.json to match the data, or "
        "restore data/ from the original dataset"
    )


@dataclass(frozen=True)
class VideoJob:
    """Decode one episode of one camera into rows ``[row_start, row_start + len(timestamps))``."""

    modality: str
    video_path: str
    timestamps: np.ndarray  # float64, in the video file's time base (8 bytes a frame, pickled as one block)
    row_start: int
    frames_dir: str  # memory-mapped frames TensorDict to write into
    image_size: tuple[int, int]
    tolerance_s: float
    source_frame_values: int  # values in one decoded frame (C * H * W at the video's resolution)
    channels: int = 3  # the modality's: 1 stores a grey (depth) video as one channel

    @property
    def frames(self) -> int:
        return len(self.timestamps)


@dataclass(frozen=True)
class ImageJob:
    """Decode a camera's images stored in the parquet files for consecutive ``episodes`` into their rows."""

    modality: str
    images: object  # the camera's one-column Hugging Face dataset (`LeRobotSource.image_column`)
    positions: np.ndarray  # int64, the rows of ``images`` for the episodes' cache rows, in order
    episodes: tuple[Episode, ...]
    frames_dir: str  # memory-mapped frames TensorDict to write into
    image_size: tuple[int, int]
    channels: int
    root: str  # the dataset root, which relative image paths start from

    @property
    def frames(self) -> int:
        return len(self.positions)


def to_cache_frames(frames, image_size: tuple[int, int], channels: int):
    """Float frames ``[n, C, h, w]`` in [0, 1] -> the cache's ``uint8 [n, channels, *image_size]``."""
    import torch
    import torch.nn.functional as F
    from torchvision.transforms.v2.functional import rgb_to_grayscale

    if frames.shape[1] != channels:  # a video decodes to RGB even when it stores one channel
        frames = rgb_to_grayscale(frames) if channels == 1 else frames.expand(-1, 3, -1, -1)
    if tuple(frames.shape[-2:]) != tuple(image_size):
        frames = F.interpolate(frames, size=image_size, mode="bilinear", antialias=True, align_corners=False)
    return (frames * 255).round_().clamp_(0, 255).to(torch.uint8)


def decode_images(entries: list, channels: int, root: Path) -> tuple[list, list[str | None]]:
    """Encoded images as ``datasets.Image`` stores them (``{"bytes", "path"}``) -> float ``[C, h, w]``
    frames in [0, 1] (``None`` where one cannot be read) and each one's error text."""
    import torch
    from torchvision.io import ImageReadMode, decode_image
    from torchvision.transforms.v2.functional import to_dtype

    mode = ImageReadMode.GRAY if channels == 1 else ImageReadMode.RGB
    frames, errors = [], []
    for entry in entries:
        try:
            data = (entry or {}).get("bytes")
            if data is None:  # a dataset that references image files instead of embedding them
                path = (entry or {}).get("path")
                if not path:
                    raise ValueError("no image bytes and no path")
                data = (root / path if not Path(path).is_absolute() else Path(path)).read_bytes()
            image = decode_image(torch.frombuffer(bytearray(data), dtype=torch.uint8), mode=mode)
            frames.append(to_dtype(image, torch.float32, scale=True))  # 8- or 16-bit (depth) PNGs alike
            errors.append(None)
        except DECODE_ERRORS as error:  # an unreadable frame means "camera absent" there
            frames.append(None)
            errors.append(_error_text(error))
    return frames, errors


def run_image_job(job: ImageJob) -> tuple[ImageJob, list[int], dict[str, str]]:
    """Decode, resize and store a job's images one episode at a time (bounded memory); return the
    cache rows whose image could not be decoded and, for the first `REPORTED_IMAGE_ERRORS` of them,
    ``{"<data dir> episode E frame F": error}``. Only decode errors are caught, as in `run_video_job`.
    """
    from tensordict import TensorDict

    destination = TensorDict.load_memmap(job.frames_dir).get(obs_key(job.modality))
    images = job.images.with_format("arrow")  # arrow rows, not one Python object per row and field
    absent, errors, read = [], {}, 0
    for episode in job.episodes:
        length = episode.stop - episode.start
        rows = images[job.positions[read : read + length].tolist()]
        read += length
        frames, failures = decode_images(rows.column(0).to_pylist(), job.channels, Path(job.root))
        stored = _episode_cache_frames(frames, job.image_size, job.channels)
        destination[episode.start : episode.stop] = stored
        for offset in (i for i, error in enumerate(failures) if error is not None):
            absent.append(episode.start + offset)
            if len(errors) < REPORTED_IMAGE_ERRORS:
                errors[f"{Path(job.root) / 'data'} episode {episode.index} frame {offset}"] = failures[offset]
    return job, absent, errors


def _episode_cache_frames(frames: list, image_size: tuple[int, int], channels: int):
    """An episode's decoded frames (``None`` where undecodable, left zero) in cache layout, resized in
    one call per frame size: the same bytes as one call per frame, without the per-call overhead."""
    import torch

    stored = torch.zeros((len(frames), channels, *image_size), dtype=torch.uint8)
    by_size: dict[tuple, list[int]] = {}
    for i, frame in enumerate(frames):
        if frame is not None:
            by_size.setdefault(tuple(frame.shape), []).append(i)
    for same in by_size.values():
        stored[same] = to_cache_frames(torch.stack([frames[i] for i in same]), image_size, channels)
    return stored


_decoder_cache = None
_decoder_file: str | None = None  # the one video file whose decoder `_decoder_cache` holds


def _decoders(video_path: str):
    """One decoder cache per process (torchcodec decoders must not cross a fork), holding only the
    decoder of ``video_path``: each open decoder keeps its FFmpeg state, and a dataset has a video
    file per few dozen episodes, so a cache of every file a worker met would grow with the dataset.
    Jobs come in episode order, so consecutive jobs of a worker mostly share the one cached file."""
    global _decoder_cache, _decoder_file
    if _decoder_cache is None:
        from lerobot.datasets.video_utils import VideoDecoderCache

        _decoder_cache = VideoDecoderCache()
    if video_path != _decoder_file:
        _decoder_cache.clear()
        _decoder_file = video_path
    return _decoder_cache


def clear_decoders() -> None:
    global _decoder_file
    if _decoder_cache is not None:
        _decoder_cache.clear()
    _decoder_file = None


def run_video_job(job: VideoJob) -> tuple[VideoJob, str | None, int]:
    """Decode, resize and store a job's frames; return the error text if the video is unreadable,
    and how many of the job's leading frames were stored.

    A video shorter than its parquet rows (the rows' timestamps run past its last frame) gives its
    frames up to its end; the error names both lengths, and the rows past the end stay undecoded.
    Only decode errors (``DECODE_ERRORS``) are caught: writing the frames is not decoding.
    """
    from lerobot.datasets.video_utils import decode_video_frames_torchcodec
    from tensordict import TensorDict

    destination = TensorDict.load_memmap(job.frames_dir).get(obs_key(job.modality))
    chunk = max(1, DECODE_CHUNK_BYTES // (4 * job.source_frame_values))
    try:
        decoded, short = _frames_in_video(job)
    except DECODE_ERRORS as error:  # an unreadable video means "camera absent", reported by file
        return job, _error_text(error), 0
    for offset in range(0, decoded, chunk):
        stamps = job.timestamps[offset : min(offset + chunk, decoded)].tolist()
        try:
            frames = decode_video_frames_torchcodec(
                job.video_path, stamps, job.tolerance_s, decoder_cache=_decoders(job.video_path)
            )  # float32 [n, 3, h, w] in [0, 1]
        except DECODE_ERRORS as error:
            return job, _error_text(error), 0
        start = job.row_start + offset
        destination[start : start + len(stamps)] = to_cache_frames(frames, job.image_size, job.channels)
    return job, short, decoded


def _frames_in_video(job: VideoJob) -> tuple[int, str | None]:
    """How many of the job's leading timestamps fall inside the video, and the error text for the
    rows past its end (``None`` when all are inside)."""
    metadata = _decoders(job.video_path).get_decoder(job.video_path).metadata
    if metadata.num_frames is None or not metadata.average_fps:
        return len(job.timestamps), None
    # The frame index lerobot's decoder looks up for each timestamp.
    indices = np.round(np.asarray(job.timestamps) * metadata.average_fps).astype(np.int64)
    past_end = np.flatnonzero(indices >= metadata.num_frames)
    if not len(past_end):
        return len(job.timestamps), None
    decoded = int(past_end[0])
    return decoded, (
        f"the video has {metadata.num_frames} frames ({metadata.num_frames / metadata.average_fps:.2f} "
        f"s), but the parquet rows of this episode need frames up to {job.timestamps[-1]:.2f} s: "
        f"its last {len(job.timestamps) - decoded} rows have no frame"
    )


def _error_text(error: BaseException) -> str:
    """``Type: first line of the message``: what the cache report records for an undecodable file."""
    return f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"


def probe_video(video_path: str, timestamps: list[float], tolerance_s: float) -> tuple[str | None, float]:
    """Decode ``timestamps`` of a video as a cache build would (lerobot's decoder, ``tolerance_s``).

    Returns the decode error (``None`` if every frame decoded) and the largest gap between a
    queried time and the frame lerobot picks for it: the ``tolerance_s`` those times would need.
    """
    from lerobot.datasets.video_utils import VideoDecoderCache, decode_video_frames_torchcodec

    decoders, gap = VideoDecoderCache(), float("nan")
    try:
        fps = decoders.get_decoder(video_path).metadata.average_fps
        gap = float(np.abs(np.asarray(timestamps) - np.round(np.asarray(timestamps) * fps) / fps).max())
        decode_video_frames_torchcodec(video_path, timestamps, tolerance_s, decoder_cache=decoders)
    except DECODE_ERRORS as error:
        return _error_text(error), gap
    finally:
        decoders.clear()
    return None, gap
