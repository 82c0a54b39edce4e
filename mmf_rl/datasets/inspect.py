"""`mmf-rl inspect DATASET`: what a LeRobot v3.0 dataset holds, and a data config to train on it.

    mmf-rl inspect /data/my_dataset                              # report + a suggested data config
    mmf-rl inspect /data/my_dataset --write-config mine.yaml     # ... written to mine.yaml
    mmf-rl train data=mine.yaml run_dir=runs/mine

The report lists every feature (dtype, shape, names), fps, episodes and frames, how `mmf-rl record`
made the dataset when it did (`mmf_rl.datasets.provenance`); for each camera, which of its video
files exist, how far the rows' ``timestamp`` drifts from ``frame_index / fps``, and whether a
sample of its frames decodes at those timestamps (as the window cache would, at the default
``tolerance_s``) and by frame index; for each numeric vector, its NaN/Inf spans and how far it
moves over the suggested horizon; and for every sensor that could be a modality, its outages: the
fraction of frames it is absent (non-finite values, a validity flag saying so, a missing video
file) and the lengths of those bursts. The suggested config maps cameras and vectors to modalities,
forecasts the target :func:`choose_target` picks (``relative`` when it moves little over the
horizon against its spread), syncs video by frame index when only that decodes, accepts the cameras
it finds absent on most frames (``allow_absent``) and, when a sensor has outages, replays them in
training (``missing: {m: {fraction, mean_burst}}``, see ``mmf_rl.datasets.config.OutageConfig``);
comments in the written file say why.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from mmf_rl.configuration import report_command_error, save_config
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.lerobot_source import (
    BOOKKEEPING_FEATURES,
    _is_numeric,
    _validity_candidates,
    open_dataset_metadata,
    probe_video,
    read_frame_columns,
)
from mmf_rl.datasets.protocols import outage_statistics
from mmf_rl.datasets.provenance import describe_provenance, read_recording_provenance
from mmf_rl.datasets.windows import MAX_ABSENT_FRACTION

CAMERA_DTYPES = ("video", "image")
# The suggested image size: the cameras' aspect kept, the longer side at most this, each side a
# multiple of IMAGE_MULTIPLE (the default image encoder halves the size 4 times).
SUGGESTED_IMAGE_SIDE = 64
IMAGE_MULTIPLE = 16
RESERVED_MODALITY_NAMES = ("target", "future_action")
SPANS_SHOWN = 5
# The suggested window, and the horizon over which a vector's motion is measured (see `_motion_ratio`).
SUGGESTED_HISTORY = SUGGESTED_HORIZON = 10
# Decoding is checked on the first, middle and last frame of this many episodes per camera.
SYNC_SAMPLE_EPISODES = 4
DEFAULT_TOLERANCE_S = DataConfig.__dataclass_fields__["tolerance_s"].default
# Target preference: the robot's own state, then the scene's, then any vector without outages.
PREFERRED_TARGETS = ("observation.state", "observation.environment_state")


def _is_vector(ft: dict) -> bool:
    return _is_numeric(ft["dtype"]) and len(ft["shape"]) == 1


def _runs(mask: np.ndarray, episode: np.ndarray) -> list[tuple[int, int]]:
    """``[first, last]`` global frame indices of the runs of True in ``mask``, cut at episode ends."""
    starts = mask.copy()
    starts[1:] &= ~mask[:-1] | (episode[1:] != episode[:-1])
    ends = mask.copy()
    ends[:-1] &= ~mask[1:] | (episode[1:] != episode[:-1])
    return list(zip(np.flatnonzero(starts).tolist(), np.flatnonzero(ends).tolist(), strict=True))


def _modality_name(feature: str, taken: set[str]) -> str:
    """``observation.images.cam_high`` -> ``cam_high``; the whole name (dots as ``_``) on a clash."""
    name = feature.rsplit(".", 1)[-1]
    if name in taken or name in RESERVED_MODALITY_NAMES:
        name = feature.replace(".", "_")
    return name


def _image_size(shape: list[int], names: list[str] | None) -> list[int]:
    names = names or ["height", "width", "channels"]
    height, width = (
        (shape[names.index("height")], shape[names.index("width")]) if "height" in names else shape[:2]
    )
    scale = min(1.0, SUGGESTED_IMAGE_SIDE / max(height, width))
    return [
        max(IMAGE_MULTIPLE, round(side * scale / IMAGE_MULTIPLE) * IMAGE_MULTIPLE) for side in (height, width)
    ]


def inspect_dataset(root: str | Path | None, repo_id: str = "local/dataset") -> dict:
    """Everything the report shows, as plain data (see the module docstring)."""
    meta = open_dataset_metadata(root, repo_id)
    root = Path(meta.root)
    features = meta.features
    episodes = [
        (int(e["episode_index"]), int(e["dataset_from_index"]), int(e["dataset_to_index"]))
        for e in meta.episodes
    ]
    cameras = [f for f, ft in features.items() if ft["dtype"] in CAMERA_DTYPES]
    vectors = [f for f, ft in features.items() if _is_vector(ft) and f not in BOOKKEEPING_FEATURES]
    validity = {
        f: next((c for c in _validity_candidates(f) if c in features), None) for f in cameras + vectors
    }
    flags = {v for v in validity.values() if v is not None}
    vectors = [f for f in vectors if f not in flags]
    columns = read_frame_columns(meta, {"episode_index", "timestamp", "frame_index", *vectors, *flags})
    n = len(columns["index"])
    episode = np.asarray(columns["episode_index"]).reshape(n)

    sensors = {}
    for feature in cameras + vectors:
        present = np.ones(n, dtype=bool)
        entry: dict = {"validity_feature": validity[feature]}
        if feature in vectors:
            values = np.asarray(columns[feature], dtype=np.float64).reshape(n, -1)
            entry.update(_vector_entry(values, episode, episodes))
            present &= np.isfinite(values).all(1)
        elif features[feature]["dtype"] == "video":
            entry.update(_video_entry(meta, feature, episodes, columns, present))
        if validity[feature] is not None:
            present &= np.asarray(columns[validity[feature]]).reshape(n, -1).astype(bool).all(1)
        entry["outages"] = outage_statistics(torch.from_numpy(present), torch.from_numpy(episode))
        sensors[feature] = entry

    return {
        "root": str(root),
        "fps": int(meta.fps),
        "episodes": len(episodes),
        "frames": int(meta.total_frames),
        "episode_frames": [stop - start for _, start, stop in episodes],
        "features": {
            f: {"dtype": ft["dtype"], "shape": list(ft["shape"]), "names": ft.get("names")}
            for f, ft in features.items()
        },
        "cameras": cameras,
        "vectors": vectors,
        "validity_features": sorted(flags),
        "sensors": sensors,
        "provenance": read_recording_provenance(root),
    }


def _video_entry(meta, feature: str, episodes: list[tuple[int, int, int]], columns: dict, present) -> dict:
    """A camera's missing video files (their episodes' frames marked absent in ``present``), the
    count of episodes without one, and how its frames' timestamps sync with the video."""
    missing = []
    for index, start, stop in episodes:
        path = Path(meta.root) / meta.get_video_file_path(index, feature)
        if not path.is_file():
            missing.append(str(path))
            present[start:stop] = False
    return {
        "video_files_missing": sorted(set(missing)),
        "episodes_without_video": len(missing),
        "sync": _video_sync(meta, feature, episodes, columns),
    }


def _vector_entry(values: np.ndarray, episode: np.ndarray, episodes: list[tuple[int, int, int]]) -> dict:
    """A vector's NaN/Inf frames and spans (frames counted from each episode's start), its motion ratio."""
    finite = np.isfinite(values).all(1)
    return {
        "nonfinite_frames": int((~finite).sum()),
        "nonfinite_spans": [
            {
                "episode": int(episode[a]),
                "frames": [a - _first(episodes, episode[a]), b - _first(episodes, episode[a])],
            }
            for a, b in _runs(~finite, episode)
        ],
        "motion_ratio": _motion_ratio(values, episode),
    }


def _first(episodes: list[tuple[int, int, int]], index: int) -> int:
    return next(start for i, start, _ in episodes if i == index)


def _motion_ratio(values: np.ndarray, episode: np.ndarray, horizon: int = SUGGESTED_HORIZON) -> float | None:
    """How far a vector moves over ``1..horizon`` frames against its spread: the mean squared change
    over those lags (within episodes) divided by its variance, averaged over the dims that vary.

    Below 1 (a position-like signal: smooth, its level far from its mean) the change from the last
    observed frame is easier to forecast than the level; near 2 (noise around a level) it is not.
    """
    finite = np.isfinite(values).all(1)
    variance = values[finite].var(0) if finite.sum() > 1 else np.zeros(values.shape[1])
    moving = variance > 0
    squares, count = np.zeros(values.shape[1]), 0
    for lag in range(1, min(horizon, len(values) - 1) + 1):
        ok = (episode[lag:] == episode[:-lag]) & finite[lag:] & finite[:-lag]
        squares += ((values[lag:][ok] - values[:-lag][ok]) ** 2).sum(0)
        count += int(ok.sum())
    if not moving.any() or count == 0:
        return None
    return float((squares[moving] / count / variance[moving]).mean())


def _video_sync(meta, feature: str, episodes: list[tuple[int, int, int]], columns: dict) -> dict | None:
    """How a camera's frames match the parquet rows: the drift of ``timestamp`` from
    ``frame_index / fps``, and whether a sample of frames decodes at the rows' timestamps (as a
    cache build does, at the default ``tolerance_s``) and by frame index (``video_sync: frame_index``).
    ``None`` when no video file of the camera is on disk."""
    root, fps = Path(meta.root), float(meta.fps)
    timestamp = np.asarray(columns["timestamp"], dtype=np.float64).reshape(-1)
    drift = timestamp - np.asarray(columns["frame_index"], dtype=np.float64).reshape(-1) / fps
    with_video = [e for e in episodes if (root / meta.get_video_file_path(e[0], feature)).is_file()]
    if not with_video:
        return None
    rows = np.concatenate([np.arange(start, stop) for _, start, stop in with_video])
    worst = int(rows[np.abs(drift[rows]).argmax()])
    result = {
        "max_drift_s": float(abs(drift[worst])),
        "drift_episode": int(np.asarray(columns["episode_index"]).reshape(-1)[worst]),
        "tolerance_s": DEFAULT_TOLERANCE_S,
        "timestamp_error": None,
        "frame_index_error": None,
        "tolerance_needed_s": 0.0,
        "sampled_frames": 0,
    }
    picks = np.unique(np.linspace(0, len(with_video) - 1, SYNC_SAMPLE_EPISODES).round().astype(int))
    for index, start, stop in (with_video[i] for i in picks):
        sample = np.unique([start, (start + stop - 1) // 2, stop - 1])
        offset = float(meta.episodes[index][f"videos/{feature}/from_timestamp"])
        path = str(root / meta.get_video_file_path(index, feature))
        error, gap = probe_video(path, (timestamp[sample] + offset).tolist(), DEFAULT_TOLERANCE_S)
        result["timestamp_error"] = result["timestamp_error"] or error
        result["tolerance_needed_s"] = max(result["tolerance_needed_s"], gap)
        error, _ = probe_video(path, ((sample - start) / fps + offset).tolist(), DEFAULT_TOLERANCE_S)
        result["frame_index_error"] = result["frame_index_error"] or error
        result["sampled_frames"] += len(sample)
    return result


def suggested_data_config(report: dict, repo_id: str = "local/dataset") -> dict:
    """A complete data config for the dataset: every camera and vector a modality, the target by
    :func:`choose_target` (``relative`` when its motion ratio is below 1), cameras synced by frame
    index when decoding at the rows' timestamps fails but by index works, cameras absent on most
    frames accepted (``allow_absent``), the sensors' outages replayed in training.
    :func:`config_comments` says why, for the written file."""
    modalities, taken = {}, set()
    for feature in report["cameras"] + report["vectors"]:
        name = _modality_name(feature, taken)
        taken.add(name)
        absent = _mostly_absent(report["sensors"][feature])
        modalities[name] = {"feature": feature, "allow_absent": True} if absent else feature
    target = choose_target(report)
    ratio = report["sensors"][target]["motion_ratio"]
    missing = {}
    for name, feature in modalities.items():
        o = report["sensors"][feature if isinstance(feature, str) else feature["feature"]]["outages"]
        if 0.0 < o["fraction"] < 1.0:
            missing[name] = {
                "fraction": round(o["fraction"], 4),
                "mean_burst": round(max(1.0, o["mean_burst"]), 2),
            }
    config = {
        "root": report["root"],
        "repo_id": repo_id,
        "history": SUGGESTED_HISTORY,
        "horizon": SUGGESTED_HORIZON,
        "stride": 1,
        "modalities": modalities,
        "target": {"feature": target, "dims": None, "relative": ratio is not None and ratio < 1.0},
        "missing": missing,
        "include_target_past": True,
        "split_fractions": [0.8, 0.1, 0.1],
        "video_sync": "frame_index" if _drifting_cameras(report) else "timestamp",
    }
    if report["cameras"]:
        first = report["features"][report["cameras"][0]]
        config["image_size"] = _image_size(first["shape"], first["names"])
    # Every key written out: a user's file is the whole data config, so `data.KEY=...` overrides any key.
    return DataConfig.from_dict(config).to_dict()


def _mostly_absent(sensor: dict) -> bool:
    """A sensor absent on more than half of the frames, or a camera whose sampled frames decode
    neither at the rows' timestamps nor by frame index (a damaged video): training loses it."""
    sync = sensor.get("sync")
    undecodable = sync is not None and sync["timestamp_error"] and sync["frame_index_error"]
    return sensor["outages"]["fraction"] > MAX_ABSENT_FRACTION or bool(undecodable)


def choose_target(report: dict) -> str:
    """The vector to forecast: ``observation.state``, else ``observation.environment_state``, else the
    first ``observation.*`` vector without outages, else any vector without, else the one absent least."""
    vectors = report["vectors"]
    if not vectors:
        raise ValueError(
            f"{report['root']}: the dataset has no numeric vector feature to forecast (features: "
            f"{sorted(report['features'])}); mmf-rl forecasts a vector such as observation.state"
        )
    absent = {f: report["sensors"][f]["outages"]["fraction"] for f in vectors}
    complete = [f for f in vectors if absent[f] == 0.0]
    return next(
        (f for f in PREFERRED_TARGETS if f in vectors),
        next(
            (f for f in complete if f.startswith("observation.")),
            complete[0] if complete else min(vectors, key=absent.get),
        ),
    )


def _drifting_cameras(report: dict) -> list[str]:
    """Cameras whose sampled frames fail to decode at the rows' timestamps but decode by frame index."""
    return [
        f
        for f in report["cameras"]
        if (sync := report["sensors"][f].get("sync"))
        and sync["timestamp_error"]
        and not sync["frame_index_error"]
    ]


def config_comments(report: dict, config: dict) -> list[str]:
    """Why the suggested config chose its target, ``relative``, ``video_sync`` and ``allow_absent``:
    comment lines for the written file."""
    target = config["target"]["feature"]
    ratio = report["sensors"][target]["motion_ratio"]
    lines = [
        f"target {target}: {' then '.join(PREFERRED_TARGETS)} come first, then a vector without outages.",
        f"relative: {str(config['target']['relative']).lower()}: over {config['horizon']} frames the "
        "target's "
        f"mean squared change is {'n/a' if ratio is None else f'{ratio:.3g}x'} its variance; below 1 the "
        "change from the last observed frame forecasts better than the level (absolute targets lost to "
        "constant velocity on real recordings).",
    ]
    for feature in _drifting_cameras(report):
        sync = report["sensors"][feature]["sync"]
        lines.append(
            f"video_sync: frame_index: {feature}'s `timestamp` drifts up to {sync['max_drift_s']:.3g} s from "
            f"frame_index/fps and its frames do not decode at it (tolerance_s={sync['tolerance_s']}); "
            "frame k of an episode is read at k/fps instead."
        )
    for name, m in config["modalities"].items():
        if m["allow_absent"]:
            sensor = report["sensors"][m["feature"]]
            sync = sensor.get("sync")
            if sync is not None and sync["timestamp_error"] and sync["frame_index_error"]:
                lines.append(
                    f"{name}: allow_absent: sampled frames of {m['feature']} decode neither at the rows' "
                    f"timestamps nor by frame index ({sync['frame_index_error'][:120]}); accepted absent, "
                    "restore or re-encode its videos to use it."
                )
                continue
            why = (
                "its video files are missing"
                if sensor.get("video_files_missing")
                else "NaN or flagged invalid"
            )
            lines.append(
                f"{name}: allow_absent: {m['feature']} is absent on {sensor['outages']['fraction']:.0%} of "
                "the "
                f"frames ({why}); accepted, or training would stop on losing it on more than half of them."
            )
    return [f"# {line}" for line in lines]


def format_report(report: dict) -> str:
    lengths = report["episode_frames"]
    lines = [
        f"dataset {report['root']}",
        f"  {report['episodes']} episodes, {report['frames']} frames at {report['fps']} fps "
        f"(episode length {min(lengths)}..{max(lengths)} frames)"
        if lengths
        else "  no episodes",
    ]
    if report["provenance"] is not None:
        lines.append(f"  {describe_provenance(report['provenance'])}")
    lines += ["", "features:"]
    for name, ft in report["features"].items():
        names = ft["names"]
        if isinstance(names, list) and len(names) > 6:
            names = names[:6] + [f"... {len(names) - 6} more"]
        lines.append(
            f"  {name:<34} {ft['dtype']:<8} {str(ft['shape']):<14} {names if names else ''}".rstrip()
        )
    lines += [
        "",
        "sensors (candidate modalities): outages = frames absent (non-finite, flagged invalid, no video)",
    ]
    for feature, s in report["sensors"].items():
        o = s["outages"]
        kind = "camera" if feature in report["cameras"] else "vector"
        head = f"  {feature} ({kind}): {o['fraction']:.1%} of frames absent" + (
            f", {o['outages']} outages, mean {o['mean_burst']:.1f} / max {o['max_burst']} frames"
            if o["outages"]
            else ""
        )
        lines.append(head)
        if s["validity_feature"]:
            lines.append(f"    validity flag: {s['validity_feature']}")
        if kind == "camera" and report["features"][feature]["dtype"] == "image":
            lines.append("    images stored in the data files (dtype image)")
        elif kind == "camera":
            missing = s["video_files_missing"]
            lines.append(
                f"    video files: {'all present' if not missing else f'{len(missing)} missing'}"
                + (
                    f" ({s['episodes_without_video']} of {report['episodes']} episodes without video)"
                    if missing
                    else ""
                )
            )
            lines += [f"      missing: {p}" for p in missing[:SPANS_SHOWN]]
            lines += _sync_lines(s.get("sync"))
        else:
            lines += _vector_lines(s)
    return "\n".join(lines)


def _vector_lines(sensor: dict) -> list[str]:
    """The report's lines on a vector: its NaN/Inf spans and how far it moves over the horizon."""
    spans = sensor["nonfinite_spans"]
    found = f"{sensor['nonfinite_frames']} frames in {len(spans)} spans" if spans else "none"
    lines = [f"    NaN/Inf: {found}"]
    lines += [
        f"      episode {sp['episode']}, frames {sp['frames'][0]}..{sp['frames'][1]}"
        for sp in spans[:SPANS_SHOWN]
    ]
    if len(spans) > SPANS_SHOWN:
        lines.append(f"      ... {len(spans) - SPANS_SHOWN} more")
    if sensor["motion_ratio"] is not None:
        lines.append(
            f"    motion over {SUGGESTED_HORIZON} frames: mean squared change / variance = "
            f"{sensor['motion_ratio']:.3g}"
        )
    return lines


def _sync_lines(sync: dict | None) -> list[str]:
    """The report's lines on how a camera's frames match the rows (see `_video_sync`)."""
    if sync is None:
        return []
    at_timestamps = (
        "decode"
        if sync["timestamp_error"] is None
        else f"FAIL ({sync['timestamp_error'][:160]}); tolerance_s >= {sync['tolerance_needed_s']:.3g} would "
        f"decode them, but a frame may then be up to {sync['max_drift_s']:.3g} s off its row"
    )
    by_index = "decode" if sync["frame_index_error"] is None else f"FAIL ({sync['frame_index_error'][:160]})"
    return [
        f"    timestamps: up to {sync['max_drift_s']:.3g} s from frame_index/fps (episode "
        f"{sync['drift_episode']})",
        f"    {sync['sampled_frames']} sampled frames at the rows' timestamps "
        f"(tolerance_s={sync['tolerance_s']}): "
        f"{at_timestamps}",
        f"    the same frames by frame index (video_sync: frame_index): {by_index}",
    ]


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mmf-rl inspect",
        description="Report what a LeRobot v3.0 dataset holds (features, cameras, NaN spans, "
        "sensor outages) and suggest a data config to train on it.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  mmf-rl inspect /data/my_dataset\n"
        "  mmf-rl inspect /data/my_dataset --write-config mine.yaml && mmf-rl train data=mine.yaml",
    )
    parser.add_argument(
        "dataset", type=Path, help="directory of a LeRobot v3.0 dataset (holding meta/info.json)"
    )
    parser.add_argument("--repo-id", default="local/dataset", help="the repo_id written into the config")
    parser.add_argument(
        "--write-config",
        type=Path,
        metavar="PATH",
        help="write the suggested data config to PATH (train with data=PATH) instead of printing it",
    )
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    from omegaconf import OmegaConf

    args = parse_args(argv)
    try:
        report = inspect_dataset(args.dataset.expanduser().resolve(), args.repo_id)
        config = suggested_data_config(report, args.repo_id)
        comments = config_comments(report, config)
    except (FileNotFoundError, NotADirectoryError, ValueError) as err:
        return report_command_error("mmf-rl inspect", err)
    print(format_report(report))
    print()
    header = (
        "# Data config suggested by `mmf-rl inspect`: edit the modalities, the target and the window,\n"
        "# then `mmf-rl train data=THIS_FILE`. `missing` replays each sensor's measured outages in "
        "training.\n" + "".join(f"{line}\n" for line in comments)
    )
    if args.write_config is not None:
        path = args.write_config.expanduser().resolve()
        save_config(config, path, header=header)
        print(f"data config written to {path}; train with: mmf-rl train data={path}")
    else:
        print("suggested data config (mmf-rl inspect DATASET --write-config PATH writes it):")
        print(header + OmegaConf.to_yaml(config), end="")
    return 0
