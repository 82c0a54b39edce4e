"""The window cache: a LeRobot dataset decoded once into memory-mapped TensorDicts.

Layout of one cache directory (``<cache_dir>/<dataset>-<fingerprint>/``):

* ``frames/`` (batch ``[N]``, one row per dataset frame, never duplicated per window):
  ``("obs", m)`` images ``uint8 [N, C, h, w]`` (resized) or raw vectors ``float32 [N, d]`` (NaN
  and ±Inf stored as 0 and marked absent), ``("present", m)`` bool, ``target`` raw ``float32
  [N, D]`` (non-finite stored as 0, ``target_valid`` False), ``target_valid``, ``episode``; with
  ``target.relative_to``, ``target_reference`` ``[N, D]`` and ``target_reference_valid`` likewise.
* ``windows/`` (batch ``[W]``): ``start`` (first observed frame), ``episode``, ``("present", m)``.
* ``cache.json``: the fingerprint, the config fields it covers, what was missing (files,
  undecodable videos with the decoder's error), what was skipped, and the size and checksum
  of every file in ``frames/`` and ``windows/``.

The directory is written under a temporary name (``.building-<pid>-<host>-...``) and renamed into
place as the last step, so a killed build never reads as a cache. The key covers every dataset
file's path, size and mtime plus the config fields that decide the content; any change gives a
new directory. Opening checks the files against their recorded sizes and checksums: a cache
changed on disk after its build is rebuilt, with a warning naming the file.

Concurrency and failures:

* Processes opening caches in one ``cache_dir`` (two ``mmf-rl train`` on the same data) take an
  exclusive lock on the directory (``flock``, released by the kernel when a process dies) around
  the check-and-build: one builds, the others wait, then open the finished cache. A reader never
  sees a half-written cache (it appears by rename); a dataset change builds a new directory,
  leaving the old one, which readers may hold, untouched.
* A build killed midway resumes: each finished decode job (one episode of a video camera, or a
  range of episodes of a camera stored as images in the parquet) is appended to ``progress.jsonl``
  in the temp dir, and the next open adopts a dead build's temp dir of the same key and decodes
  only the jobs not listed. The temp dirs of other dead builds are removed.
* Before a build, the frames' size is checked against the free space (a memory-mapped write to
  a full disk is a SIGBUS, not an error); ``ENOSPC`` from a write removes the partial build and
  says so. The previous caches are untouched either way.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import glob
import hashlib
import itertools
import json
import logging
import multiprocessing
import os
import re
import shutil
import sys
import tempfile
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict
from tqdm.auto import tqdm

from mmf_rl import keys
from mmf_rl.datasets.lerobot_source import (
    REPORTED_IMAGE_ERRORS,
    ImageJob,
    LeRobotSource,
    VideoJob,
    clear_decoders,
    run_image_job,
    run_video_job,
)
from mmf_rl.temp_dirs import is_stale, owned_temp_prefix, remove_stale_temp_dirs

logger = logging.getLogger(__name__)

# 2: cache.json records each file's size and checksum; 3: Inf targets stored as 0, windows need a
# finite target at their last observed frame
CACHE_FORMAT = 3
CACHE_META = "cache.json"
BUILDING_PREFIX = ".building-"
# In a build's temp dir: one JSON line per finished decode job, and the marker written once the
# frame table is allocated and its vector columns filled (what a resumed build keeps).
PROGRESS_FILE = "progress.jsonl"
FRAMES_READY = "frames.ready"
# Free space a build leaves beyond the cache's own size (cache.json, filesystem slack).
FREE_SPACE_MARGIN = 64 * 2**20
# Checksums: files up to this size are hashed whole (cheap next to opening the cache; see docs/results.md);
# larger ones (image frames) by their size plus CHECKSUM_SAMPLES blocks of CHECKSUM_BLOCK bytes
# spread from the first to the last byte, so an open stays cheap for a cache of any size.
FULL_CHECKSUM_MAX_BYTES = 64 * 2**20
CHECKSUM_BLOCK = 2**20
CHECKSUM_SAMPLES = 16
# A spawned decode worker pays seconds of imports (torch, torchvision via lerobot): below this
# many frames, decoding in-process is faster than starting a pool.
POOL_MIN_FRAMES = 3000
# Jobs per decode process for the cameras stored as images (their episodes split by frames): enough
# that the processes finish together and the progress bar moves, few enough to keep each job's
# start-up (opening the frame table and the images) negligible.
IMAGE_JOBS_PER_WORKER = 8
# Windows checked at once when the cache's windows are listed: bounds the frame-index matrices
# (history + horizon int64s per window) to a few tens of MB whatever the dataset's size.
WINDOW_CHUNK = 2**16


def fingerprint(source: LeRobotSource) -> str:
    """Hash of the dataset's files (relative path, size, mtime) and the content-deciding config."""
    digest = hashlib.sha256()
    key = {"format": CACHE_FORMAT, "config": source.config.cache_fields()}
    if not source.selected_all:  # only then: caches of whole datasets keep their key
        key["episodes"] = [e.index for e in source.episodes]
    digest.update(json.dumps(key, sort_keys=True).encode())
    for path in source.files():
        stat = path.stat()
        digest.update(f"{path.relative_to(source.root)}\0{stat.st_size}\0{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:24]


def cache_path(source: LeRobotSource) -> Path:
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", source.root.name or source.config.repo_id)
    return source.config.resolved_cache_dir() / f"{name}-{fingerprint(source)}"


def window_offsets(history: int, horizon: int, stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Frame offsets from a window's first observed frame: observed steps, then forecast steps."""
    observed = torch.arange(history) * stride
    future = (history - 1) * stride + torch.arange(1, horizon + 1) * stride
    return observed, future


def action_offsets(history: int, horizon: int, stride: int) -> torch.Tensor:
    """Frame offsets (from a window's first frame) of the actions over the horizon: the last
    observed frame's action up to the one before the last forecast frame (``T·stride`` frames)."""
    return (history - 1) * stride + torch.arange(horizon * stride)


def _as_matrix(column: np.ndarray, n: int) -> np.ndarray:
    return np.asarray(column, dtype=np.float32).reshape(n, -1)


def _vector_column(column: np.ndarray, dims: list[int] | None, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A vector feature's frames ``[n, d]`` (selected ``dims``; NaN/Inf → 0) and where they were finite."""
    values = _as_matrix(column, n)
    if dims is not None:
        values = values[:, dims]
    finite = np.isfinite(values).all(1)
    return torch.from_numpy(np.nan_to_num(values, nan=0.0, posinf=0.0, neginf=0.0)), torch.from_numpy(finite)


def _frame_columns(source: LeRobotSource, columns: dict[str, np.ndarray]) -> dict:
    """Per-frame vectors (NaN/Inf → 0), per-frame presence from non-finite values and validity features."""
    n = len(columns["index"])
    obs, present = {}, {}
    for name, m in source.modalities.items():
        ok = torch.ones(n, dtype=torch.bool)
        if not m.is_camera:
            obs[name], finite = _vector_column(columns[m.feature], m.dims, n)
            ok &= finite
        if m.valid_feature is not None:
            ok &= torch.from_numpy(np.asarray(columns[m.valid_feature]).reshape(n, -1).astype(bool).all(1))
        present[name] = ok
    target, target_valid = _vector_column(columns[source.target_feature], source.config.target.dims, n)
    per_frame = {
        keys.OBS: obs,
        keys.PRESENT: present,
        "target": target,
        "target_valid": target_valid,
        "episode": torch.from_numpy(np.asarray(columns["episode_index"], dtype=np.int64)),
    }
    if source.reference_feature is not None:
        per_frame["target_reference"], per_frame["target_reference_valid"] = _vector_column(
            columns[source.reference_feature], source.config.target.relative_to.dims, n
        )
    if source.action_feature is not None:
        per_frame["action"], per_frame["action_valid"] = _vector_column(
            columns[source.action_feature], source.config.action.dims, n
        )
    return per_frame


def _camera_jobs(
    source: LeRobotSource, columns: dict, frames_dir: Path, missing: dict, num_workers: int | None
) -> list[ImageJob | VideoJob]:
    """The decode jobs of every camera: those stored as images first (their errors come first in the
    report), then the videos'. The image jobs are split for the processes the whole build would use,
    so a resumed build splits them as the killed one did."""
    videos = _video_jobs(source, columns, frames_dir, missing)
    cameras = sum(m.storage == "image" for m in source.modalities.values())
    frames = sum(j.frames for j in videos) + cameras * sum(e.stop - e.start for e in source.episodes)
    parts = IMAGE_JOBS_PER_WORKER * max(_worker_count(num_workers, frames), 1)
    return _image_jobs(source, frames_dir, parts) + videos


def _image_jobs(source: LeRobotSource, frames_dir: Path, parts: int) -> list[ImageJob]:
    """Per camera stored as images, ``parts`` jobs of consecutive episodes with about as many frames
    each (fewer when there are fewer episodes)."""
    lengths = np.array([e.stop - e.start for e in source.episodes])
    part_of = ((np.cumsum(lengths) - lengths) * parts // max(int(lengths.sum()), 1)).tolist()
    jobs = []
    for name, m in source.modalities.items():
        if m.storage != "image":
            continue
        images, row_order = source.image_column(name)
        for _, group in itertools.groupby(zip(part_of, source.episodes, strict=True), key=lambda p: p[0]):
            episodes = tuple(e for _, e in group)
            jobs.append(
                ImageJob(
                    modality=name,
                    images=images,
                    positions=np.concatenate([row_order[e.start : e.stop] for e in episodes]),
                    episodes=episodes,
                    frames_dir=str(frames_dir),
                    image_size=tuple(source.config.image_size),
                    channels=m.spec.shape[0],
                    root=str(source.root),
                )
            )
    return jobs


def _video_jobs(
    source: LeRobotSource, columns: dict, frames_dir: Path, missing: dict[str, list[Path]]
) -> list[VideoJob]:
    jobs = []
    for name, m in source.modalities.items():
        if not m.is_video:
            continue
        absent = set(missing.get(name, []))
        for episode in source.episodes:
            path = source.video_path(episode.index, m.feature)
            if path in absent:
                continue
            offset = source.video_from_timestamp(episode.index, m.feature)
            stamps = _episode_times(source, columns, episode) + offset
            jobs.append(
                VideoJob(
                    modality=name,
                    video_path=str(path),
                    timestamps=stamps,
                    row_start=episode.start,
                    frames_dir=str(frames_dir),
                    image_size=tuple(source.config.image_size),
                    tolerance_s=source.config.tolerance_s,
                    source_frame_values=int(np.prod(source.features[m.feature]["shape"])),
                    channels=m.spec.shape[0],
                )
            )
    return jobs


def _episode_times(source: LeRobotSource, columns: dict, episode) -> np.ndarray:
    """The times (from the episode's start in its video) of the video frames an episode's rows read."""
    if source.config.video_sync == "frame_index":
        return np.arange(episode.stop - episode.start, dtype=np.float64) / source.meta.fps
    return columns["timestamp"][episode.start : episode.stop].astype(np.float64)


def _job_key(job: ImageJob | VideoJob) -> str:
    if isinstance(job, ImageJob):
        return f"{job.modality}:{job.episodes[0].start}-{job.episodes[-1].stop}:parquet images"
    return f"{job.modality}:{job.row_start}:{job.video_path}"


def _job_record(job: ImageJob | VideoJob, *result) -> dict:
    """What a finished job leaves to mark and report (its line in the progress file): for a video, its
    error or None and how many leading frames it decoded; for images, the rows of the undecodable
    ones and the first errors."""
    if isinstance(job, ImageJob):
        absent, errors = result
        return {"absent": absent, "errors": errors}
    error, decoded = result
    return {"error": error, "decoded": decoded}


def _finished_jobs(progress: Path) -> dict[str, dict]:
    """Job key -> `_job_record` of the jobs a build recorded as finished."""
    finished = {}
    if progress.is_file():
        for line in progress.read_text().splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:  # the line being written when the build was killed
                continue
            finished[record.pop("job")] = record
    return finished


def _worker_count(num_workers: int | None, frames: int) -> int:
    """``num_workers``, or by default one process per core when there are enough frames to repay
    their start-up."""
    if num_workers is not None:
        return num_workers
    return len(os.sched_getaffinity(0)) if frames >= POOL_MIN_FRAMES else 1


def _runner(job: ImageJob | VideoJob):
    """The function that decodes ``job``, looked up when called (tests replace them)."""
    return run_image_job if isinstance(job, ImageJob) else run_video_job


def _decode(
    jobs: list[ImageJob | VideoJob], num_workers: int | None, progress: Path, done_frames: int = 0
) -> dict[str, dict]:
    """Run the decode jobs (process pool with ``spawn`` when worth it); return each one's
    `_job_record` by `_job_key`.

    Each finished job is appended to ``progress`` (its frames are in the memory-mapped table by
    then), so a killed build can resume after it.
    """
    total = sum(j.frames for j in jobs)
    workers = min(_worker_count(num_workers, total), len(jobs))
    records = {}
    with (
        tqdm(
            total=total + done_frames,
            initial=done_frames,
            desc="decoding cameras into the window cache",
            unit="frame",
            disable=not jobs,
        ) as bar,
        open(progress, "a") as log,
    ):

        def finished(job: ImageJob | VideoJob, *result) -> None:
            records[_job_key(job)] = _job_record(job, *result)
            log.write(json.dumps({"job": _job_key(job), **records[_job_key(job)]}) + "\n")
            log.flush()
            bar.update(job.frames)

        if workers > 1:
            # spawn, not fork: torchcodec decoders break in forked children; each spawned worker
            # starts with its own empty decoder cache. One torch thread each: the workers already
            # fill the cores, and torch's default (a thread per core) in every worker oversubscribes
            # them and slows the build several-fold (docs/results.md).
            context = multiprocessing.get_context("spawn")
            with ProcessPoolExecutor(
                max_workers=workers, mp_context=context, initializer=torch.set_num_threads, initargs=(1,)
            ) as pool:
                # Each finished future is dropped: kept, their results would hold every job twice.
                pending = {pool.submit(_runner(job), job): job for job in jobs}
                for future in as_completed(pending):
                    finished(pending.pop(future), *future.result()[1:])
        else:
            try:
                for job in jobs:
                    finished(*_runner(job)(job))
            finally:
                clear_decoders()
    return records


def _write(source: LeRobotSource, directory: Path, num_workers: int | None) -> dict:
    """Build the cache's files in ``directory``; continue the build a killed process left there."""
    frames, unordered, missing, jobs = _frame_table(source, directory, num_workers)
    n = int(frames.batch_size[0])
    records = _decode_cameras(jobs, directory, num_workers)
    undecodable = _mark_undecodable_and_missing(source, frames, jobs, records, missing)

    windows, skipped = _windows(source, frames)
    skipped["episodes_timestamps_not_increasing"] = unordered
    shutil.rmtree(directory / "windows", ignore_errors=True)  # a killed build may have begun them
    windows.memmap_(directory / "windows")
    report = {
        "format": CACHE_FORMAT,
        "config": source.config.cache_fields(),
        "dataset_root": str(source.root),
        "n_frames": n,
        "n_windows": int(windows.batch_size[0]),
        "specs": [s.to_dict() for s in source.specs],
        "target_dim": source.target_dim,
        "action_dim": source.action_dim,
        "episodes": [[e.index, e.start, e.stop] for e in source.episodes],
        "missing_files": {name: [str(p) for p in paths] for name, paths in missing.items()},
        "undecodable_files": undecodable,
        "skipped": skipped,
    }
    (directory / PROGRESS_FILE).unlink()
    (directory / FRAMES_READY).unlink()
    report["files"] = _file_records(directory)
    (directory / CACHE_META).write_text(json.dumps(report, indent=2))
    return report


def _frame_table(
    source: LeRobotSource, directory: Path, num_workers: int | None
) -> tuple[TensorDict, list[int], dict, list[ImageJob | VideoJob]]:
    """The frame table with its vector columns filled (a killed build's, or allocated now), the
    episodes skipped for unordered timestamps, the missing videos and the camera decode jobs.

    The dataset's columns live only in this call: the decoding that follows holds none of them.
    """
    columns = source.read_columns()
    # Synced by frame index, the (wall-clock) timestamps match no video frame: their order does not matter.
    by_index = source.config.video_sync == "frame_index"
    unordered = [] if by_index else source.drop_episodes_with_unordered_timestamps(columns)
    missing = source.missing_videos()
    jobs = _camera_jobs(source, columns, directory / "frames", missing, num_workers)
    if (directory / FRAMES_READY).is_file():
        frames = TensorDict.load_memmap(directory / "frames")
    else:
        frames = _allocate_frames(source, _frame_columns(source, columns), directory / "frames")
        (directory / FRAMES_READY).touch()
    return frames, unordered, missing, jobs


def _decode_cameras(jobs: list, directory: Path, num_workers: int | None) -> dict[str, dict]:
    """Decode the jobs a killed build did not finish; the `_job_record` of every job, by
    `_job_key`, from this build or the killed one."""
    finished = _finished_jobs(directory / PROGRESS_FILE)
    todo = [job for job in jobs if _job_key(job) not in finished]
    if finished:
        logger.info(
            "resuming an interrupted window cache build in %s: %d of %d decode jobs already done",
            directory,
            len(jobs) - len(todo),
            len(jobs),
        )
    done_frames = sum(j.frames for j in jobs) - sum(j.frames for j in todo)
    return finished | _decode(todo, num_workers, directory / PROGRESS_FILE, done_frames)


def _mark_undecodable_and_missing(
    source: LeRobotSource, frames: TensorDict, jobs: list, records: dict, missing: dict
) -> dict:
    """Clear the presence of the frames that the jobs could not decode and of the episodes whose
    video file is missing; per modality, the undecodable video files or the first undecodable
    images (`REPORTED_IMAGE_ERRORS`), with their errors."""
    undecodable: dict[str, dict[str, str]] = {}
    for job in jobs:  # in job order: the report is the same whichever job finished first
        record, present = records[_job_key(job)], frames.get(keys.present_key(job.modality))
        if isinstance(job, ImageJob):
            present[torch.tensor(record["absent"], dtype=torch.long)] = False
            for where, error in record["errors"].items():
                reported = undecodable.setdefault(job.modality, {})
                if len(reported) < REPORTED_IMAGE_ERRORS:
                    reported[where] = error
        elif record["error"] is not None:
            undecodable.setdefault(job.modality, {})[job.video_path] = record["error"]
            present[job.row_start + record["decoded"] : job.row_start + job.frames] = False
    for name, paths in missing.items():
        absent = {str(p) for p in paths}
        for episode in source.episodes:
            if str(source.video_path(episode.index, source.modalities[name].feature)) in absent:
                frames.get(keys.present_key(name))[episode.start : episode.stop] = False
    return undecodable


def _allocate_frames(source: LeRobotSource, per_frame: dict, frames_dir: Path) -> TensorDict:
    """The memory-mapped frame table with its vector columns filled (images come from decoding)."""
    n = len(per_frame["episode"])
    shutil.rmtree(frames_dir, ignore_errors=True)  # a killed build's half-allocated table
    layout = {
        keys.OBS: {
            name: torch.zeros((), dtype=m.spec.dtype).expand(n, *m.spec.shape)
            for name, m in source.modalities.items()
        },
        keys.PRESENT: per_frame[keys.PRESENT],
        "target": per_frame["target"],
        "target_valid": per_frame["target_valid"],
        "episode": per_frame["episode"],
    }
    vector_keys = ["target", "target_valid", "episode"]
    for key in ("target_reference", "target_reference_valid"):
        if key in per_frame:
            vector_keys.append(key)
            layout[key] = per_frame[key]
    if "action" in per_frame:
        vector_keys += ["action", "action_valid"]
        layout.update(action=per_frame["action"], action_valid=per_frame["action_valid"])
    frames = TensorDict(layout, batch_size=[n]).memmap_like(frames_dir)
    # memmap_like only allocates the files; fill the vector columns (images come from decoding).
    for key in vector_keys:
        frames.get(key).copy_(layout[key])
    for name in source.modalities:
        frames.get(keys.present_key(name)).copy_(per_frame[keys.PRESENT][name])
        if name in per_frame[keys.OBS]:
            frames.get(keys.obs_key(name)).copy_(per_frame[keys.OBS][name])
    return frames


def _windows(source: LeRobotSource, frames: TensorDict) -> tuple[TensorDict, dict]:
    """Every in-episode window that has a finite target and at least one present modality.

    The target must be finite at the forecast steps and at the last observed frame: a relative
    target is measured from that frame (``relative`` is applied at batch time, not cached); so
    must ``target.relative_to``'s feature at that frame. With an action feature, the actions over
    the horizon must be finite too.
    """
    config = source.config
    span = int(window_offsets(config.history, config.horizon, config.stride)[1][-1])
    starts, too_short = [], []
    for episode in source.episodes:
        if episode.stop - episode.start > span:
            starts.append(torch.arange(episode.start, episode.stop - span))
        else:
            too_short.append(episode.index)
    starts = torch.cat(starts) if starts else torch.zeros(0, dtype=torch.long)
    # Per chunk of windows: their frame-index matrices are ~8 bytes per frame of every window.
    chunks = [_window_checks(source, frames, chunk) for chunk in starts.split(WINDOW_CHUNK)]
    present = {name: torch.cat([c[0][name] for c in chunks]) for name in source.modalities}
    target_ok = torch.cat([c[1] for c in chunks])
    action_ok = torch.cat([c[2] for c in chunks])
    any_present = torch.stack(list(present.values())).any(0)
    keep = target_ok & any_present & action_ok
    windows = TensorDict(
        {
            "start": starts[keep],
            "episode": frames.get("episode").as_subclass(torch.Tensor)[starts[keep]],
            keys.PRESENT: {name: mask[keep] for name, mask in present.items()},
        },
        batch_size=[int(keep.sum())],
    )
    skipped = {
        "episodes_too_short": too_short,
        "min_episode_frames": span + 1,
        "windows_target_not_finite": int((~target_ok).sum()),
        "windows_without_any_modality": int((target_ok & ~any_present).sum()),
        "windows_action_not_finite": int((target_ok & any_present & ~action_ok).sum()),
    }
    return windows, skipped


def _window_checks(
    source: LeRobotSource, frames: TensorDict, starts: torch.Tensor
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """For the windows at ``starts``: each modality's presence, whether the target (and its
    reference) is finite where it must be, and whether the actions over the horizon are."""
    config = source.config
    observed, future = window_offsets(config.history, config.horizon, config.stride)
    observed_rows = starts[:, None] + observed
    last_rows = starts + int(observed[-1])
    present = {}
    for name, m in source.modalities.items():
        frame_present = frames.get(keys.present_key(name)).as_subclass(torch.Tensor)
        present[name] = (
            frame_present[last_rows] if m.spec.kind == "vector" else frame_present[observed_rows].all(1)
        )
    target_valid = frames.get("target_valid").as_subclass(torch.Tensor)
    target_ok = target_valid[starts[:, None] + future].all(1) & target_valid[last_rows]
    if config.include_target_past:
        target_ok &= target_valid[observed_rows].all(1)
    if source.reference_feature is not None:
        target_ok &= frames.get("target_reference_valid").as_subclass(torch.Tensor)[last_rows]
    action_ok = torch.ones_like(target_ok)
    if source.action_feature is not None:
        action_valid = frames.get("action_valid").as_subclass(torch.Tensor)
        action_ok = action_valid[
            starts[:, None] + action_offsets(config.history, config.horizon, config.stride)
        ].all(1)
    return present, target_ok, action_ok


def _checksum(path: Path) -> str:
    size = path.stat().st_size
    with open(path, "rb") as f:
        if size <= FULL_CHECKSUM_MAX_BYTES:
            return hashlib.file_digest(f, "sha256").hexdigest()
        digest = hashlib.sha256()
        for offset in np.linspace(0, size - CHECKSUM_BLOCK, CHECKSUM_SAMPLES).astype(np.int64).tolist():
            f.seek(offset)
            digest.update(f.read(CHECKSUM_BLOCK))
        return digest.hexdigest()


def _file_records(directory: Path) -> dict[str, dict]:
    """Size and checksum of every file of the cache's TensorDicts (memmaps and their meta.json)."""
    return {
        str(path.relative_to(directory)): {"size": path.stat().st_size, "sha256": _checksum(path)}
        for sub in ("frames", "windows")
        for path in sorted((directory / sub).rglob("*"))
        if path.is_file()
    }


def cache_damage(directory: Path) -> str | None:
    """What differs between the cache at ``directory`` and what its build recorded; None if nothing."""
    meta = directory / CACHE_META
    try:
        recorded = json.loads(meta.read_text())["files"]
    except FileNotFoundError:
        return f"{meta} is missing"
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as error:
        return f"{meta} is unreadable ({type(error).__name__}: {error})"
    for name, expected in recorded.items():
        path = directory / name
        if not path.is_file():
            return f"{path} is missing"
        size = path.stat().st_size
        if size != expected["size"]:
            return f"{path} has {size} bytes, the build wrote {expected['size']}"
        if _checksum(path) != expected["sha256"]:
            return f"{path} has changed since the build (sha256 differs)"
    return None


def _temp_prefix(name: str) -> str:
    return f"{owned_temp_prefix(BUILDING_PREFIX)}{name}-"


def remove_stale_builds(cache_dir: Path) -> None:
    """Delete the temp dirs under ``cache_dir`` that killed builds left behind (never a live one)."""
    remove_stale_temp_dirs(cache_dir, BUILDING_PREFIX)


def _discard(directory: Path) -> None:
    """Remove a damaged cache: renamed to a temp dir first, so no reader ever sees it half-deleted."""
    trash = Path(tempfile.mkdtemp(prefix=_temp_prefix(directory.name), dir=directory.parent))
    with contextlib.suppress(FileNotFoundError):  # another process discarded it first
        os.rename(directory, trash)  # replaces the empty temp dir
    shutil.rmtree(trash, ignore_errors=True)


def _refuse_reimported_main(cache_dir: Path) -> None:
    """A spawned worker re-imports the parent's main script; if that script opens the cache at module
    level (no ``if __name__ == "__main__":`` guard), the worker would wait forever for the lock its own
    parent holds while the parent waits for the worker."""
    frame = sys._getframe()  # "__mp_main__" is the name a spawned process runs the parent's script under
    while frame is not None:
        if frame.f_code.co_name == "<module>" and frame.f_globals.get("__name__") == "__mp_main__":
            raise RuntimeError(
                f"a worker process re-ran your script {frame.f_globals.get('__file__')} and reached the "
                f"window cache in {cache_dir}, which its parent holds: it would wait forever. Put the "
                'script\'s top-level code under `if __name__ == "__main__":` (worker processes are '
                "spawned and import the main script again)"
            )
        frame = frame.f_back


@contextlib.contextmanager
def _locked(cache_dir: Path):
    """An exclusive ``flock`` on the cache directory itself: no lock file to leave behind, and the
    kernel releases it when its holder dies (a killed build never blocks the next one)."""
    fd = os.open(cache_dir, os.O_RDONLY)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _refuse_reimported_main(cache_dir)
            logger.info("waiting for another process to finish with the window caches in %s ...", cache_dir)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _resumable_build(destination: Path) -> Path | None:
    """A dead build's temp dir for ``destination`` with its frame table allocated, renamed to this
    process's name (so no other process takes it for stale); None if there is none."""
    pattern = f"{glob.escape(BUILDING_PREFIX)}*-{glob.escape(destination.name)}-*"
    for directory in sorted(destination.parent.glob(pattern)):
        if (directory / FRAMES_READY).is_file() and is_stale(directory, BUILDING_PREFIX):
            claimed = Path(tempfile.mkdtemp(prefix=_temp_prefix(destination.name), dir=destination.parent))
            os.rename(directory, claimed)  # replaces the empty temp dir
            return claimed
    return None


def estimated_size(source: LeRobotSource) -> int:
    """Bytes of the frame table of ``source``'s cache (the windows add a few bytes per frame)."""
    per_frame = 8 + 4 * source.target_dim + 1  # episode, target, target_valid
    if source.reference_feature is not None:
        per_frame += 4 * source.target_dim + 1
    if source.action_dim is not None:
        per_frame += 4 * source.action_dim + 1
    for m in source.modalities.values():
        per_frame += int(np.prod(m.spec.shape)) * (1 if m.is_video else 4) + 1
    return source.meta.total_frames * per_frame


def _check_free_space(source: LeRobotSource, cache_dir: Path) -> None:
    needed, free = estimated_size(source), shutil.disk_usage(cache_dir).free
    if needed + FREE_SPACE_MARGIN > free:
        raise OSError(
            errno.ENOSPC,
            f"the window cache of {source.root} needs about {needed / 2**30:.2f} GiB "
            f"({source.meta.total_frames} frames) in {cache_dir}, which has "
            f"{free / 2**30:.2f} GiB free; free space there, or set data.cache_dir to a "
            "disk with room (nothing was written)",
        )


def open_cache(source: LeRobotSource, num_workers: int | None = None) -> tuple[Path, dict, bool]:
    """The cache directory of ``source``, its report, and whether it was built by this call.

    Under the cache directory's lock: adopts a killed build of this cache to resume it, removes
    stale temp dirs of other killed builds, and builds if no cache exists. A cache whose files no
    longer match what its build recorded is discarded and rebuilt, with a warning naming the file.
    """
    destination = cache_path(source)
    destination.parent.mkdir(parents=True, exist_ok=True)
    with _locked(destination.parent):
        resume = None if destination.exists() else _resumable_build(destination)
        remove_stale_builds(destination.parent)
        if destination.exists():
            damage = cache_damage(destination)
            if damage is None:
                return destination, json.loads((destination / CACHE_META).read_text()), False
            warnings.warn(f"window cache {destination} is damaged: {damage}; rebuilding it", stacklevel=3)
            _discard(destination)
        build_cache(source, destination, num_workers, resume)
    return destination, json.loads((destination / CACHE_META).read_text()), True


def build_cache(
    source: LeRobotSource, destination: Path, num_workers: int | None = None, resume: Path | None = None
) -> None:
    """Decode ``source`` into ``destination`` atomically (temp dir, then rename); ``resume``: a
    killed build's temp dir to continue (see `open_cache`)."""
    destination.parent.mkdir(parents=True, exist_ok=True)
    if resume is None:
        _check_free_space(source, destination.parent)
    building = resume or Path(tempfile.mkdtemp(prefix=_temp_prefix(destination.name), dir=destination.parent))
    try:
        _write(source, building, num_workers)
        os.chmod(building, 0o755)  # mkdtemp makes it private; a finished cache is as readable as any
        try:
            os.rename(building, destination)
        except OSError:
            if not (destination / CACHE_META).is_file():
                raise
            shutil.rmtree(building)  # a concurrent build finished first; its cache is identical
    except OSError as error:
        shutil.rmtree(building, ignore_errors=True)
        if error.errno == errno.ENOSPC:
            raise OSError(
                errno.ENOSPC,
                f"no space left on device while building the window cache {destination} "
                f"({error}); the partial build was removed, nothing else changed: free "
                f"space in {destination.parent}, or set data.cache_dir to a disk with "
                "room",
            ) from None
        raise
    except BaseException:
        shutil.rmtree(building, ignore_errors=True)
        raise
