"""How the window cache's cost grows with the dataset: build time, peak RSS, batch throughput.

    .venv/bin/python benchmarks/cache_scale.py                  # N = 10k, 100k, 500k, 1M frames
    .venv/bin/python benchmarks/cache_scale.py --quick          # N = 10k only
    .venv/bin/python benchmarks/cache_scale.py --sizes 20000 --work-dir /data/scale

For each N a synthetic LeRobot v3.0 dataset (`benchmarks.synthetic.dataset`, lerobot's own writer:
a 64x64 video camera, state, force and pose vectors, episodes of 250 frames) is written once
under ``--work-dir`` and reused by later runs (lerobot's writer is slow at 1M frames: docs/results.md
gives its time). Its cache is built in a fresh subprocess, which reports its wall
time and peak RSS (``VmHWM`` of itself and of its decode workers); batches of 256 train windows are
then read from the cache in another fresh subprocess, which reports their throughput and its peak
RSS (what a training process's loader holds). Targets: build time linear in N, peak RSS (build,
decode workers and reader) < 1.2 GB at 1M frames, throughput flat.

Then the largest N (or ``--resume-size``) is built again and SIGKILLed once ~90% of its video jobs
are recorded in ``progress.jsonl``; the next build must resume: it reports how many jobs were
already decoded and decodes only the rest.

Prints a table, then ``summary:`` with the ratios against the smallest N measured in the same run
(build seconds per frame, throughput) and the resume's outcome.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # the checkout: `benchmarks.synthetic` importable, run as a script
EPISODE_FRAMES = 250
IMAGE_SIZE = 64
BATCH_SIZE = 256
MAX_BATCHES = 100
RESUME_AT = 0.9
POLL_S = 0.05
# lerobot's writer appends each episode to the current video file by remuxing the whole file, so
# writing is quadratic until the file reaches ``video_files_size_in_mb`` (default 200 MB; a 64x64
# episode is ~18 KB, so 500k frames would be one 36 MB file rewritten 2000 times). 1 MB files
# (~56 episodes each) keep the writer linear and give the cache many files, as real datasets have.
VIDEO_FILE_MB = 1


def data_config(root: Path, cache_dir: Path):
    from benchmarks.synthetic.dataset import FORCE_FEATURE, IMAGE_FEATURE, POSE_FEATURE, STATE_FEATURE
    from mmf_rl.datasets.config import DataConfig

    return DataConfig.from_dict(
        {
            "root": str(root),
            "cache_dir": str(cache_dir),
            "history": 10,
            "horizon": 10,
            "image_size": [IMAGE_SIZE, IMAGE_SIZE],
            "split_fractions": [0.8, 0.1, 0.1],
            "modalities": {"image": IMAGE_FEATURE, "state": STATE_FEATURE, "force": FORCE_FEATURE},
            "target": {"feature": POSE_FEATURE, "dims": [0, 1]},
        }
    )


def dataset(work_dir: Path, frames: int) -> Path:
    """The synthetic dataset of ``frames`` frames, written once.

    A partial or older-layout one is rewritten.
    """
    from benchmarks.synthetic.dataset import make_synthetic_dataset

    root = work_dir / f"synthetic-{frames}"
    done = root / ".complete"
    layout = f"video_files_size_in_mb={VIDEO_FILE_MB}"
    if not done.is_file() or done.read_text() != layout:
        shutil.rmtree(root, ignore_errors=True)
        episodes = [EPISODE_FRAMES] * (frames // EPISODE_FRAMES)
        episodes += [frames % EPISODE_FRAMES] if frames % EPISODE_FRAMES else []
        started = time.perf_counter()
        make_synthetic_dataset(
            root,
            episodes,
            image_size=IMAGE_SIZE,
            nan_force_episodes=(),
            invalid_image_episodes=(),
            video_files_size_in_mb=VIDEO_FILE_MB,
        )
        print(
            f"wrote {root} ({frames} frames, {len(episodes)} episodes) in "
            f"{time.perf_counter() - started:.0f} s",
            flush=True,
        )
        done.write_text(layout)
    return root


def subprocess_command(root: Path, cache_dir: Path, mode: str = "--build") -> list[str]:
    return [sys.executable, str(Path(__file__).resolve()), mode, str(root), str(cache_dir)]


def peak_rss_mb(pid: int | str = "self") -> float:
    """A process's own peak RSS (``VmHWM``), 0 if it has exited.

    Not ``ru_maxrss``: a process started by (v)fork + exec inherits its parent's peak into it, so
    the build subprocess would report this script's peak (its pages of the previous size's cache).
    """
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return 0.0
    return int(re.search(r"^VmHWM:\s+(\d+) kB", status, re.MULTILINE)[1]) / 1024


def child_pids() -> set[int]:
    """This process's children, whichever of its threads started them."""
    pids = set()
    for task in Path("/proc/self/task").iterdir():
        with contextlib.suppress(FileNotFoundError):  # a thread that ended meanwhile
            pids.update(int(pid) for pid in (task / "children").read_text().split())
    return pids


class WorkerPeaks:
    """The largest own peak RSS of this process's children (the decode workers), polled until stopped."""

    def __init__(self):
        self.peaks: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()

    def _poll(self) -> None:
        while not self._stop.wait(POLL_S):
            for pid in child_pids():
                self.peaks[pid] = max(self.peaks.get(pid, 0.0), peak_rss_mb(pid))

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return max(self.peaks.values(), default=0.0)


def build_in_this_process(root: Path, cache_dir: Path) -> None:
    """The subprocess side: build (or resume) the cache, print one JSON line with time and peak RSS."""
    from mmf_rl.datasets.windows import WindowDataset

    # The library's records on stderr: `interrupted_build` reads the resume record there.
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    workers = WorkerPeaks()
    started = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        WindowDataset(data_config(root, cache_dir))
    elapsed = time.perf_counter() - started
    print(json.dumps({"build_s": elapsed, "rss_mb": peak_rss_mb(), "workers_rss_mb": workers.stop()}))


def subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return env


def measure_in_subprocess(root: Path, cache_dir: Path, mode: str = "--build") -> tuple[dict, str]:
    """Run this script in ``mode`` (``--build`` or ``--read``) in a fresh process; its JSON line."""
    result = subprocess.run(
        subprocess_command(root, cache_dir, mode),
        env=subprocess_env(),
        capture_output=True,
        text=True,
        check=False,
    )
    if result.returncode != 0:
        sys.exit(f"cache {mode[2:]} failed ({result.returncode}):\n{result.stderr[-3000:]}")
    return json.loads(result.stdout.strip().splitlines()[-1]), result.stderr


def read_in_this_process(root: Path, cache_dir: Path) -> None:
    """The reader side: throughput from the built cache and this process's peak RSS, as one JSON line."""
    windows_s = measure_throughput(root, cache_dir)
    print(json.dumps({"windows_s": windows_s, "read_rss_mb": peak_rss_mb()}))


def measure_throughput(root: Path, cache_dir: Path) -> float:
    """Train windows per second over up to MAX_BATCHES batches of BATCH_SIZE (after one warm-up batch)."""
    from mmf_rl.datasets.windows import WindowDataset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        data = WindowDataset(data_config(root, cache_dir))
    batches = iter(data.loader("train", BATCH_SIZE, seed=0))
    next(batches)
    windows, started = 0, time.perf_counter()
    for index, batch in enumerate(batches):
        windows += batch.shape[0]
        if index + 1 >= MAX_BATCHES:
            break
    return windows / (time.perf_counter() - started)


def interrupted_build(root: Path, cache_dir: Path, episodes: int) -> str:
    """Kill a build at ~90% of its video jobs, build again; describe what the second build did."""
    shutil.rmtree(cache_dir, ignore_errors=True)
    process = subprocess.Popen(
        subprocess_command(root, cache_dir),
        env=subprocess_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )

    def recorded() -> int:
        return sum(len(p.read_text().splitlines()) for p in cache_dir.glob(".building-*/progress.jsonl"))

    while recorded() < RESUME_AT * episodes:
        if process.poll() is not None:
            return (
                f"the build ended (exit {process.returncode}) before {RESUME_AT:.0%} of its jobs: not "
                "interrupted"
            )
        time.sleep(POLL_S)
    os.killpg(process.pid, signal.SIGKILL)  # the build and its decode workers
    process.wait()
    killed_at = recorded()
    stats, stderr = measure_in_subprocess(root, cache_dir)
    resumed = re.search(r"resuming an interrupted window cache build .*: (\d+) of (\d+) decode jobs", stderr)
    if resumed is None:
        return (
            f"killed at {killed_at}/{episodes} jobs; the next build started over (no resume) in "
            f"{stats['build_s']:.1f} s"
        )
    return (
        f"killed at {killed_at}/{episodes} jobs; the next build resumed with {resumed[1]} of {resumed[2]} "
        f"done and decoded the other {int(resumed[2]) - int(resumed[1])} in {stats['build_s']:.1f} s"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 500_000, 1_000_000])
    parser.add_argument("--quick", action="store_true", help="N = 10k only")
    parser.add_argument("--work-dir", type=Path, default=Path("/tmp/mmf_rl_cache_scale"))
    parser.add_argument(
        "--resume-size",
        type=int,
        default=None,
        help="N of the dataset whose build is killed at ~90%% and resumed (default: the largest N)",
    )
    parser.add_argument("--build", nargs=2, type=Path, metavar=("ROOT", "CACHE_DIR"), help=argparse.SUPPRESS)
    parser.add_argument("--read", nargs=2, type=Path, metavar=("ROOT", "CACHE_DIR"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.build or args.read:
        (build_in_this_process if args.build else read_in_this_process)(*(args.build or args.read))
        return
    sizes = [10_000] if args.quick else sorted(args.sizes)
    args.work_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for frames in sizes:
        root = dataset(args.work_dir, frames)
        cache_dir = args.work_dir / f"cache-{frames}"
        shutil.rmtree(cache_dir, ignore_errors=True)
        stats, _ = measure_in_subprocess(root, cache_dir)
        rows.append({"frames": frames, **stats, **measure_in_subprocess(root, cache_dir, "--read")[0]})
        shutil.rmtree(cache_dir, ignore_errors=True)
        r = rows[-1]
        print(
            f"N={frames}: build {r['build_s']:.1f} s, peak RSS {r['rss_mb']:.0f} MB (decode workers "
            f"{r['workers_rss_mb']:.0f} MB), {r['windows_s']:.0f} windows/s (reader "
            f"{r['read_rss_mb']:.0f} MB)",
            flush=True,
        )

    print(
        f"\n{'frames':>8} {'build s':>9} {'ms/1k fr':>9} {'RSS MB':>8} {'wkr MB':>8} {'windows/s':>10} "
        f"{'read MB':>8}"
    )
    for r in rows:
        print(
            f"{r['frames']:>8} {r['build_s']:>9.1f} {1e6 * r['build_s'] / r['frames']:>9.1f} "
            f"{r['rss_mb']:>8.0f} "
            f"{r['workers_rss_mb']:>8.0f} {r['windows_s']:>10.0f} {r['read_rss_mb']:>8.0f}"
        )
    killed = args.resume_size or sizes[-1]
    resume = interrupted_build(
        dataset(args.work_dir, killed),
        args.work_dir / f"cache-{killed}-resume",
        episodes=-(-killed // EPISODE_FRAMES),
    )
    shutil.rmtree(args.work_dir / f"cache-{killed}-resume", ignore_errors=True)
    first, last = rows[0], rows[-1]
    per_frame = (last["build_s"] / last["frames"]) / (first["build_s"] / first["frames"])
    peak = max(last["rss_mb"], last["workers_rss_mb"], last["read_rss_mb"])
    print(
        f"summary: build s/frame at N={last['frames']} is {per_frame:.2f}x that at N={first['frames']} "
        f"(linear: ~1); peak RSS at N={last['frames']} {peak:.0f} MB ({'<' if peak < 1200 else '>='} 1.2 GB "
        "target); "
        f"throughput {last['windows_s'] / first['windows_s']:.2f}x (flat: ~1); resume at N={killed}: {resume}"
    )


if __name__ == "__main__":  # spawned decode workers import this file as __mp_main__: nothing runs
    main()
