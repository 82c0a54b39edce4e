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
forecasts the target :func:`choose_target` picks by the features' names (the robot's state before
the commands sent to it; ``relative`` when it moves little over the horizon against its spread),
syncs video by frame index when only that decodes, accepts the cameras it finds absent on most
frames (``allow_absent``), leaves out (as a commented-out entry) a sensor absent on every frame and,
when a sensor has outages, replays them in training (``missing: {m: {fraction, mean_burst}}``, see
``mmf_rl.datasets.config.OutageConfig``); comments in the written file say why. Files the dataset
declares but that sit under a near-miss path (``video/`` for ``videos/``, ``chunk_000`` for
``chunk-000``) are reported with the rename that fixes them, never read there.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import numpy as np
import torch

from mmf_rl.configuration import report_command_error, write_text_atomic
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.lerobot_source import (
    BOOKKEEPING_FEATURES,
    INFO_FILE,
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
# Missing files (and the renames that fix near misses) a report line shows; it then says how many more.
FILES_SHOWN = 3
ALTERNATIVES_SHOWN = 5
# Words (split at anything but letters) that name the commands sent to a robot, or one of its positions.
COMMAND_WORDS = re.compile(r"action|command|cmd|ctrl|control|goal|setpoint|target")
POSITION_WORDS = re.compile(r"q?pos(e|ition)?s?|joints?|angles?")


def _words(feature: str) -> list[str]:
    return re.findall(r"[a-z]+", feature.lower())


def _named_command(feature: str) -> bool:
    return any(COMMAND_WORDS.match(w) for w in _words(feature))


def _named_state(feature: str) -> bool:
    return "state" in feature.lower() and not _named_command(feature)


def _named_position(feature: str) -> bool:
    return any(POSITION_WORDS.fullmatch(w) for w in _words(feature)) and not _named_command(feature)


# How the target is picked: the first rule a vector meets ranks it (a forecast of the robot's state
# is what a user of a recording wants, not of the commands sent to it); within a rule, the vector
# absent least, then the dataset's order. Each rule: its label in the written comment, its test.
TARGET_RULES = (
    ("observation.state (LeRobot's robot state)", lambda f: f == "observation.state"),
    ("observation.environment_state (LeRobot's scene state)", lambda f: f == "observation.environment_state"),
    ("named as a state (state, *.state, observation.*state*)", _named_state),
    ("named as a position (pos, position, pose, joint, angle)", _named_position),
    ("another observation.* vector", lambda f: f.startswith("observation.") and not _named_command(f)),
    ("a vector not named as a command", lambda f: not _named_command(f)),
    ("named as an action or command (action, command, cmd, control, goal, target)", lambda f: True),
)


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
    _check_data_files(meta, episodes)
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
    root, missing = Path(meta.root), []
    for index, start, stop in episodes:
        path = root / meta.get_video_file_path(index, feature)
        if not path.is_file():
            missing.append(path)
            present[start:stop] = False
    misses = near_misses(root, sorted(set(missing)))
    return {
        "video_files_missing": sorted({str(p) for p in missing}),
        "episodes_without_video": len(missing),
        "near_misses": len(misses),
        "renames": [[str(a), str(b)] for a, b in _renames(root, misses)],  # relative to the root
        "sync": _video_sync(meta, feature, episodes, columns),
    }


def _check_data_files(meta, episodes: list[tuple[int, int, int]]) -> None:
    """Refuse data files under a near-miss of info.json's ``data_path`` (``chunk_000`` for
    ``chunk-000``): lerobot's loader reads whatever ``data/*/*.parquet`` holds, so the report would
    describe files the dataset does not name. Other missing files are left to the loader's error."""
    root = Path(meta.root)
    declared = sorted({root / meta.get_data_file_path(index) for index, _, _ in episodes})
    absent = [p for p in declared if not p.is_file()]
    misses = near_misses(root, absent)
    if misses:
        raise FileNotFoundError(
            f"{root / INFO_FILE}: `data_path` {meta.data_path!r} names {len(absent)} data file(s) that "
            f"are missing, e.g. {absent[0]}; {len(misses)} of them are under a near-miss path, not read "
            f"there: {rename_advice(root, _renames(root, misses))}, then run `mmf-rl inspect` again"
        )


def _loose_key(relative: Path) -> tuple:
    """A relative path as it reads ignoring case, separators, zero padding and a plural ``s``:
    ``video/cam/chunk_0/file_000.mp4`` reads as ``videos/cam/chunk-000/file-000.mp4``."""
    return tuple(
        tuple(int(t) if t.isdigit() else t.rstrip("s") for t in re.findall(r"[a-z]+|\d+", part.lower()))
        for part in relative.parts
    )


def near_misses(root: Path, expected: list[Path]) -> dict[Path, Path]:
    """Of the ``expected`` files (absent), those another file under ``root`` matches by
    :func:`_loose_key`: expected path -> the file found. Only reported: renaming makes it the dataset's."""
    found: dict[tuple, Path] = {}
    for suffix in sorted({p.suffix for p in expected}):
        for path in sorted(root.rglob(f"*{suffix}")):
            found.setdefault(_loose_key(path.relative_to(root)), path)
    keys = {p: _loose_key(p.relative_to(root)) for p in expected}
    return {p: found[k] for p, k in keys.items() if k in found}


def _renames(root: Path, misses: dict[Path, Path]) -> list[tuple[Path, Path]]:
    """The renames (paths relative to ``root``) that put near-miss files where info.json says: the
    first misnamed folder when the rest of the path matches (``video/`` -> ``videos/``; one level
    deeper while the right name exists, as ``videos/`` does when other cameras are in place), else
    the file itself."""
    renames = set()
    for expected, found in misses.items():
        want, have = expected.relative_to(root).parts, found.relative_to(root).parts
        first = next(i for i, (a, b) in enumerate(zip(want, have, strict=True)) if a != b)
        if want[first + 1 :] != have[first + 1 :]:
            renames.add((Path(*have), Path(*want)))
            continue
        level = next(j for j in range(first, len(want)) if not root.joinpath(*want[: j + 1]).exists())
        renames.add((Path(*have[: level + 1]), Path(*want[: level + 1])))
    return sorted(renames)


def rename_advice(root: str | Path, renames: list[tuple[Path, Path]] | list[list[str]]) -> str:
    """``in ROOT rename A to B, ...``: the first FILES_SHOWN renames and how many more."""
    shown = ", ".join(f"{a} to {b}" for a, b in renames[:FILES_SHOWN])
    more = len(renames) - FILES_SHOWN
    return f"in {root} rename {shown}" + (f" (and {more} more like them)" if more > 0 else "")


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
    """A complete data config for the dataset: every camera and vector present on some frame a
    modality (:func:`left_out` lists the others), the target by :func:`choose_target` (``relative``
    when its motion ratio is below 1), cameras synced by frame index when decoding at the rows'
    timestamps fails but by index works, cameras absent on most frames accepted (``allow_absent``),
    the sensors' outages replayed in training. :func:`config_text` writes it with why, as comments."""
    names = modality_names(report)
    modalities = {}
    for feature, name in names.items():
        if not _never_present(report["sensors"][feature]):
            absent = _mostly_absent(report["sensors"][feature])
            modalities[name] = {"feature": feature, "allow_absent": True} if absent else feature
    if not modalities:
        causes = "; ".join(f"{f}: {_absence_cause(report['sensors'][f], report['root'])}" for f in names)
        raise ValueError(
            f"{report['root']}: every sensor is absent on every frame ({causes}); restore what the "
            "report finds missing before training on it"
        )
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
    # A left-out camera still sets the size: its commented-out entry then trains as it is once restored.
    cameras = [f for f in report["cameras"] if names[f] in modalities] or report["cameras"]
    if cameras:
        first = report["features"][cameras[0]]
        config["image_size"] = _image_size(first["shape"], first["names"])
    # Every key written out: a user's file is the whole data config, so `data.KEY=...` overrides any key.
    return DataConfig.from_dict(config).to_dict()


def modality_names(report: dict) -> dict[str, str]:
    """Each camera's and vector's modality name (see `_modality_name`), left-out ones included so
    that leaving one out renames no other."""
    names: dict[str, str] = {}
    for feature in report["cameras"] + report["vectors"]:
        names[feature] = _modality_name(feature, set(names.values()))
    return names


def _never_present(sensor: dict) -> bool:
    return sensor["outages"]["fraction"] == 1.0


def left_out(report: dict) -> list[str]:
    """The sensors absent on every frame: a modality of them could never be present in a window."""
    return [f for f in report["cameras"] + report["vectors"] if _never_present(report["sensors"][f])]


def _absence_cause(sensor: dict, root: str) -> str:
    """Why the report finds a sensor absent: missing video files (and the renames that would
    restore them), NaN/Inf values, its validity flag."""
    if sensor.get("video_files_missing"):
        count = len(sensor["video_files_missing"])
        cause = f"{count} video file{'s' if count > 1 else ''} missing"
        if sensor["near_misses"]:
            cause += (
                f"; {sensor['near_misses']} of them are under a near-miss path, not read there: "
                f"{rename_advice(root, sensor['renames'])}"
            )
        return cause
    causes = ["NaN or Inf values"] if sensor.get("nonfinite_frames") else []
    if sensor["validity_feature"]:
        causes.append(f"flagged invalid by {sensor['validity_feature']}")
    return " or ".join(causes)


def _mostly_absent(sensor: dict) -> bool:
    """A sensor absent on more than half of the frames, or a camera whose sampled frames decode
    neither at the rows' timestamps nor by frame index (a damaged video): training loses it."""
    sync = sensor.get("sync")
    undecodable = sync is not None and sync["timestamp_error"] and sync["frame_index_error"]
    return sensor["outages"]["fraction"] > MAX_ABSENT_FRACTION or bool(undecodable)


def ranked_targets(report: dict) -> list[tuple[str, str]]:
    """Every vector as ``(feature, label of the TARGET_RULES rule it meets)``, the best target first;
    a vector absent on more than half of the frames comes after every other."""
    vectors = report["vectors"]
    if not vectors:
        raise ValueError(
            f"{report['root']}: the dataset has no numeric vector feature to forecast (features: "
            f"{sorted(report['features'])}); mmf-rl forecasts a vector such as observation.state"
        )
    absent = {f: _absent(report, f) for f in vectors}
    rule = {f: next(i for i, (_, meets) in enumerate(TARGET_RULES) if meets(f)) for f in vectors}
    ranked = sorted(vectors, key=lambda f: (absent[f] > MAX_ABSENT_FRACTION, rule[f], absent[f]))
    return [(f, TARGET_RULES[rule[f]][0]) for f in ranked]


def choose_target(report: dict) -> str:
    """The vector to forecast: the first of :func:`ranked_targets`."""
    return ranked_targets(report)[0][0]


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
    lines = _target_comments(report, target) + [
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
    lines += [
        _allow_absent_comment(name, m["feature"], report["sensors"][m["feature"]], report["root"])
        for name, m in config["modalities"].items()
        if m["allow_absent"]
    ]
    return [f"# {line}" for line in lines]


def _target_comments(report: dict, target: str) -> list[str]:
    """The rule that picked the target, and the other vectors it could be, best first."""
    ranked = ranked_targets(report)
    label = dict(ranked)[target]
    others = [_alternative(f, rule, _absent(report, f)) for f, rule in ranked if f != target]
    shown = ", ".join(others[:ALTERNATIVES_SHOWN]) + (
        f" and {len(others) - ALTERNATIVES_SHOWN} more" if len(others) > ALTERNATIVES_SHOWN else ""
    )
    return [
        f'target {target}: picked by the rule "{label}"; a vector named as a state ranks before '
        "positions, other observations and, last, actions and commands; within a rule, the one absent "
        "least.",
        f"target alternatives, best first: {shown}; set target.feature to one to forecast it instead."
        if others
        else "target alternatives: none, it is the dataset's only vector.",
    ]


def _alternative(feature: str, rule: str, absent: float) -> str:
    return f"{feature} [{rule}" + (f", absent on {absent:.0%} of the frames]" if absent else "]")


def _absent(report: dict, feature: str) -> float:
    return report["sensors"][feature]["outages"]["fraction"]


def _allow_absent_comment(name: str, feature: str, sensor: dict, root: str) -> str:
    sync = sensor.get("sync")
    if sync is not None and sync["timestamp_error"] and sync["frame_index_error"]:
        return (
            f"{name}: allow_absent: sampled frames of {feature} decode neither at the rows' "
            f"timestamps nor by frame index ({sync['frame_index_error'][:120]}); accepted absent, "
            "restore or re-encode its videos to use it."
        )
    return (
        f"{name}: allow_absent: {feature} is absent on {sensor['outages']['fraction']:.0%} of the frames "
        f"({_absence_cause(sensor, root)}); accepted, or training would stop on losing it on more than half "
        "of them."
    )


def config_text(report: dict, config: dict) -> str:
    """The written file: a header saying why (:func:`config_comments`), the config, and under
    ``modalities`` each :func:`left_out` sensor as a commented-out entry with the reason."""
    from omegaconf import OmegaConf

    header = (
        "# Data config suggested by `mmf-rl inspect`: edit the modalities, the target and the window,\n"
        "# then `mmf-rl train data=THIS_FILE`. `missing` replays each sensor's measured outages in "
        "training.\n" + "".join(f"{line}\n" for line in config_comments(report, config))
    )
    lines = OmegaConf.to_yaml(config).splitlines(keepends=True)
    names = modality_names(report)
    entries = [_left_out_entry(report, feature, names[feature]) for feature in left_out(report)]
    at = lines.index("modalities:\n") + 1
    return header + "".join(lines[:at] + entries + lines[at:])


def _left_out_entry(report: dict, feature: str, name: str) -> str:
    cause = _absence_cause(report["sensors"][feature], report["root"])
    return (
        f"  # {name} left out: absent on all {report['frames']} frames ({cause}); uncomment once it is "
        f"present:\n  # {name}: {feature}\n"
    )


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
        if _never_present(s):
            lines.append(
                "    left out of the suggested config (a commented-out entry): absent on every frame"
            )
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
            lines += _missing_file_lines(s, report["root"])
            lines += _sync_lines(s.get("sync"))
        else:
            lines += _vector_lines(s)
    return "\n".join(lines)


def _missing_file_lines(sensor: dict, root: str) -> list[str]:
    """The report's lines on a camera's missing video files: the first few, and the near misses."""
    missing = sensor["video_files_missing"]
    lines = [f"      missing: {p}" for p in missing[:SPANS_SHOWN]]
    if len(missing) > SPANS_SHOWN:
        lines.append(f"      ... {len(missing) - SPANS_SHOWN} more")
    if sensor["near_misses"]:
        lines.append(
            f"    {sensor['near_misses']} of them are under a near-miss path (not read there): "
            f"{rename_advice(root, sensor['renames'])}"
        )
    return lines


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
    args = parse_args(argv)
    try:
        report = inspect_dataset(args.dataset.expanduser().resolve(), args.repo_id)
        text = config_text(report, suggested_data_config(report, args.repo_id))
    except (FileNotFoundError, NotADirectoryError, ValueError) as err:
        return report_command_error("mmf-rl inspect", err)
    print(format_report(report))
    print()
    if args.write_config is not None:
        path = args.write_config.expanduser().resolve()
        write_text_atomic(path, text)
        print(f"data config written to {path}; train with: mmf-rl train data={path}")
    else:
        print("suggested data config (mmf-rl inspect DATASET --write-config PATH writes it):")
        print(text, end="")
    return 0
