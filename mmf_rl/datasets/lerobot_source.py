"""Reading a LeRobot v3.0 dataset through lerobot's own metadata, parquet and video utilities.

Only what lerobot does not provide lives here: mapping features to modalities, finding which
video files exist, and decoding whole episodes (resized, uint8) straight into the window cache.
lerobot is imported lazily: importing it costs seconds, and spawned decode workers only need
its video utilities.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mmf_rl.datasets.config import DataConfig
from mmf_rl.keys import ModalitySpec

# Bytes of decoded frames per decode call: lerobot returns float32 frames at full resolution,
# so a call covers many small frames (fast) but only a few HD ones (bounded memory).
DECODE_CHUNK_BYTES = 64 * 2**20


@dataclass(frozen=True)
class ResolvedModality:
    """A modality after checking its config against the dataset's features."""

    spec: ModalitySpec
    feature: str
    dims: list[int] | None
    valid_feature: str | None

    @property
    def is_video(self) -> bool:
        return self.spec.kind == "image"


@dataclass(frozen=True)
class Episode:
    index: int
    start: int  # first global frame index
    stop: int  # one past the last


def open_metadata(config: DataConfig):
    """``LeRobotDatasetMetadata`` for a local ``root`` (never downloads) or the hub ``repo_id``."""
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    if config.root is None:
        meta = LeRobotDatasetMetadata(config.repo_id)
        # The hub path: fetch data and videos the way lerobot does; absent videos stay absent.
        meta.pull_from_repo(allow_patterns=["data/*", "videos/*"])
        return meta
    root = Path(config.root)
    if not (root / "meta" / "info.json").is_file():
        raise FileNotFoundError(
            f"{root} is not a LeRobot dataset: {root / 'meta' / 'info.json'} does not exist "
            "(set `root` to the directory holding meta/, data/ and videos/)"
        )
    return LeRobotDatasetMetadata(config.repo_id, root=root)


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


def _check_dims(dims: list[int] | None, width: int, what: str) -> None:
    if dims is not None and (not dims or min(dims) < 0 or max(dims) >= width):
        raise ValueError(f"{what}: dims {dims} out of range for a feature of width {width} (valid: 0..{width - 1})")


class LeRobotSource:
    """A LeRobot dataset seen through a :class:`DataConfig`: modalities resolved, files located."""

    def __init__(self, config: DataConfig):
        self.config = config
        self.meta = open_metadata(config)
        self.root = Path(self.meta.root)
        self.features: dict[str, dict] = self.meta.features
        self.modalities = {name: self._resolve(name) for name, _ in sorted(config.modalities.items())}
        self.target_feature = self._require_feature(config.target.feature, "target")
        target_width = self._vector_width(self.target_feature, "target")
        _check_dims(config.target.dims, target_width, f"target {self.target_feature!r}")
        self.target_dim = len(config.target.dims) if config.target.dims is not None else target_width
        self.episodes = [
            Episode(int(e["episode_index"]), int(e["dataset_from_index"]), int(e["dataset_to_index"]))
            for e in self.meta.episodes
        ]

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
        if ft["dtype"] in ("video", "image", "string") or len(ft["shape"]) != 1:
            raise ValueError(
                f"{what}: feature {feature!r} must be a vector (1-D numeric), found dtype {ft['dtype']!r} "
                f"shape {list(ft['shape'])}"
            )
        return int(ft["shape"][0])

    def _resolve(self, name: str) -> ResolvedModality:
        cfg = self.config.modalities[name]
        what = f"modality {name!r}"
        feature = self._require_feature(cfg.feature, what)
        ft = self.features[feature]
        if ft["dtype"] == "image":
            raise ValueError(
                f"{what}: feature {feature!r} stores images inside the parquet files (dtype 'image'); "
                "mmf-rl reads cameras from videos: record the dataset with use_videos=True"
            )
        if ft["dtype"] == "video":
            if cfg.kind not in (None, "image"):
                raise ValueError(f"{what}: feature {feature!r} is a video, so kind must be 'image', found {cfg.kind!r}")
            names = ft.get("names") or ["height", "width", "channels"]
            channels = int(ft["shape"][names.index("channels")]) if "channels" in names else 3
            shape = (channels, *self.config.image_size)
            kind, dims = "image", None
        else:
            width = self._vector_width(feature, what)
            _check_dims(cfg.dims, width, f"{what} ({feature!r})")
            kind = cfg.kind or "sequence"
            if kind == "image":
                raise ValueError(f"{what}: feature {feature!r} is a vector, so kind cannot be 'image'")
            dims = cfg.dims
            shape = (len(dims) if dims is not None else width,)
        valid = cfg.valid_feature
        if valid is not None:
            self._require_feature(valid, f"{what} valid_feature")
        else:
            valid = next((c for c in _validity_candidates(feature) if c in self.features), None)
        spec = ModalitySpec(name=name, kind=kind, shape=shape, encoder=cfg.encoder, required=cfg.required)
        return ResolvedModality(spec=spec, feature=feature, dims=dims, valid_feature=valid)

    def video_path(self, episode: int, feature: str) -> Path:
        return self.root / self.meta.get_video_file_path(episode, feature)

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
        """The per-frame columns the pipeline needs, ordered by the global frame ``index``."""
        from lerobot.datasets.utils import get_hf_features_from_features, load_nested_dataset

        columns = {"index", "episode_index", "timestamp", self.target_feature}
        for m in self.modalities.values():
            if not m.is_video:
                columns.add(m.feature)
            if m.valid_feature is not None:
                columns.add(m.valid_feature)
        hf = load_nested_dataset(self.root / "data", features=get_hf_features_from_features(self.features))
        data = hf.select_columns(sorted(columns)).with_format("numpy")[:]
        order = np.argsort(data["index"], kind="stable")
        data = {k: np.asarray(v)[order] for k, v in data.items()}
        expected = np.arange(self.meta.total_frames)
        if len(data["index"]) != len(expected) or not np.array_equal(data["index"], expected):
            raise ValueError(
                f"{self.root / 'data'}: frame `index` column should be 0..{len(expected) - 1} "
                f"(meta/info.json total_frames={len(expected)}), found {len(data['index'])} rows "
                f"from {data['index'].min() if len(data['index']) else None} to "
                f"{data['index'].max() if len(data['index']) else None}"
            )
        return data

    def files(self) -> list[Path]:
        """Every file that makes up the dataset: what the cache fingerprint covers."""
        return sorted(p for sub in ("meta", "data", "videos") for p in (self.root / sub).rglob("*") if p.is_file())


@dataclass(frozen=True)
class VideoJob:
    """Decode one episode of one camera into rows ``[row_start, row_start + len(timestamps))``."""

    modality: str
    video_path: str
    timestamps: tuple[float, ...]  # in the video file's time base
    row_start: int
    frames_dir: str  # memory-mapped frames TensorDict to write into
    image_size: tuple[int, int]
    tolerance_s: float
    source_frame_values: int  # values in one decoded frame (C * H * W at the video's resolution)


_decoder_cache = None


def _decoders():
    """One decoder cache per process: torchcodec decoders must not cross a fork."""
    global _decoder_cache
    if _decoder_cache is None:
        from lerobot.datasets.video_utils import VideoDecoderCache

        _decoder_cache = VideoDecoderCache()
    return _decoder_cache


def clear_decoders() -> None:
    if _decoder_cache is not None:
        _decoder_cache.clear()


def run_video_job(job: VideoJob) -> tuple[VideoJob, str | None]:
    """Decode, resize and store a job's frames; return the error text if the video is unreadable."""
    import torch
    import torch.nn.functional as F
    from lerobot.datasets.video_utils import decode_video_frames_torchcodec
    from tensordict import TensorDict

    destination = TensorDict.load_memmap(job.frames_dir).get(("obs", job.modality))
    chunk = max(1, DECODE_CHUNK_BYTES // (4 * job.source_frame_values))
    try:
        for offset in range(0, len(job.timestamps), chunk):
            stamps = list(job.timestamps[offset : offset + chunk])
            frames = decode_video_frames_torchcodec(
                job.video_path, stamps, job.tolerance_s, decoder_cache=_decoders()
            )  # float32 [n, C, h, w] in [0, 1]
            if tuple(frames.shape[-2:]) != job.image_size:
                frames = F.interpolate(frames, size=job.image_size, mode="bilinear", antialias=True, align_corners=False)
            start = job.row_start + offset
            destination[start : start + len(stamps)] = (frames * 255).round_().clamp_(0, 255).to(torch.uint8)
    except Exception as error:  # noqa: BLE001 - any decoder failure means "camera absent", reported by file
        return job, f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"
    return job, None
