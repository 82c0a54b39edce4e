"""The frame every script around the protocol shares (``mmf-rl compare`` and the benchmarks built on
it): the flags of a run, a named budget its flags override, the push recording made when absent, one
timed pass of the protocol and its two result files. One copy here keeps the scripts' flags, defaults
and recordings the same, so two benchmarks asking for the same push episodes share one recording."""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from mmf_rl.compare.collect import Collected, collect_runs
from mmf_rl.compare.entries import Budget, Entry, Study, select_entries
from mmf_rl.compare.runs import check_entries, check_reused, open_data, run_pending

if TYPE_CHECKING:
    from mmf_rl.datasets import WindowDataset

logger = logging.getLogger(__name__)
# The flags a mode's value stands in for, with their help.
OVERRIDE_FLAGS = {
    "seeds": {"type": int, "nargs": "+", "help": "override the mode's seeds"},
    "steps": {"type": int, "help": "override the mode's training steps"},
    "batch-size": {"type": int, "help": "override the mode's batch size"},
}


def add_run_flags(parser: argparse.ArgumentParser) -> None:
    """``--device`` and ``--jobs``: where the runs train and how many at once."""
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (passed to train and eval)")
    parser.add_argument(
        "--jobs", type=int, default=1, help="runs trained at once, each with cores/jobs threads"
    )


def add_override_flags(parser: argparse.ArgumentParser, *names: str) -> None:
    """The ``OVERRIDE_FLAGS`` named (``seeds``, ``steps``, ``batch-size``): each replaces a mode's value."""
    for name in names:
        parser.add_argument(f"--{name}", default=None, **OVERRIDE_FLAGS[name])


def check_run_flags(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    catalogue: Sequence[Entry] | None = None,
    paper_required: bool = True,
) -> None:
    """A usage error (exit 2, before anything runs) for ``--jobs`` below 1 and, given the ``catalogue``,
    for ``--entries`` naming an entry it lacks (or leaving out the paper model, when the summaries
    compare every row with it)."""
    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, found {args.jobs}")
    if catalogue is not None and args.entries is not None:
        try:
            select_entries(catalogue, args.entries, paper_required)
        except ValueError as err:
            parser.error(f"--{err}")


@dataclass(frozen=True)
class Mode:
    """A benchmark's named budget (``--tiny``, ``--standard``, ...): what every run trains with, the
    entries it runs and the push episodes recorded when its data is absent."""

    image_size: int
    batch_size: int
    steps: int
    seeds: tuple[int, ...]
    entries: tuple[str, ...] | None  # None: every entry
    episodes: int  # recorded when the data does not exist

    @property
    def budget(self) -> Budget:
        return Budget(self.steps, self.batch_size, self.seeds, self.image_size)

    def overridden(self, args: argparse.Namespace) -> Mode:
        """This mode with what the flags give (``--seeds``, ``--steps``, ``--batch-size``,
        ``--entries``) in place of its own; a flag left out keeps the mode's value."""
        given = {name: getattr(args, name, None) for name in ("seeds", "steps", "batch_size", "entries")}
        return dataclasses.replace(
            self, **{name: tuple(v) if isinstance(v, list) else v for name, v in given.items() if v}
        )


def push_study(
    args: argparse.Namespace,
    catalogue: Sequence[Entry],
    modalities: Sequence[str],
    paper_required: bool = True,
    retrained_for: tuple[str, ...] | None = None,
) -> Study:
    """The study of a push benchmark's parsed flags: ``args.budget`` (a :class:`Mode`) on the recording
    ``args.data``, its runs and results in ``args.out``."""
    mode = args.budget
    return Study(
        out=args.out,
        budget=mode.budget,
        entries=tuple(select_entries(catalogue, mode.entries, paper_required)),
        modalities=tuple(modalities),
        data_overrides=(f"data.root={args.data}",),
        device=args.device,
        jobs=args.jobs,
        retrained_for=retrained_for,
    )


def push_recording_path(repository: Path, episodes: int) -> Path:
    """Where the benchmarks keep the push recording of ``episodes`` episodes by default."""
    return repository / "data" / f"push_bench_{episodes}ep"


def recorded_episodes(root: Path) -> int | None:
    """``total_episodes`` of the LeRobot dataset's ``meta/info.json`` (None without one)."""
    info = root / "meta" / "info.json"
    return json.loads(info.read_text()).get("total_episodes") if info.is_file() else None


@dataclass(frozen=True)
class PushRecording:
    """The benchmarks' push dataset: ``episodes`` of 50 steps at 64x64 (the recorder's defaults), seed
    0, recorded into ``root`` when it does not exist."""

    root: Path
    episodes: int

    def make_if_absent(self) -> float | None:
        """Record it with ``mmf-rl record`` (two workers) unless ``root`` exists; the recording's wall
        seconds, None when it existed. In a child process, as recording here would leave lerobot's
        handler on the root logger behind, doubling every later progress message; its stdout is
        dropped, as this process's stdout is the benchmark's report (its progress shows on stderr)."""
        if self.root.exists():
            return None
        command = [sys.executable, "-m", "mmf_rl.cli", "record", "--out", str(self.root)]
        command += ["--episodes", str(self.episodes), "--workers", "2", "--image-size", "64"]
        command += ["--steps", "50", "--seed", "0"]
        logger.info("recording %d push episodes: %s", self.episodes, " ".join(command))
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        return time.perf_counter() - start


def check_study(study: Study, title: str) -> None:
    """Exit with a message naming the script (``title``) if an entry does not compose, or ``study.out``
    holds completed runs of another budget or config: seconds after the start instead of after the
    first trainings."""
    try:
        check_entries(study)
        check_reused(study)
    except ValueError as err:
        raise SystemExit(f"{title}: {err}") from None


@dataclass
class Outcome:
    """One pass of the protocol: the data's splits, every run's results and what the pass cost."""

    data: WindowDataset  # its splits name the test episodes and windows
    collected: Collected
    runs: int  # runs the entries need
    reused: int  # of them, completed by an earlier invocation
    record_seconds: float | None  # None: the recording existed
    cache_seconds: float
    seconds: float  # the whole pass, recording and cache included

    def info(self) -> dict[str, Any]:
        """The pass's times, run counts and reference error: what every report's ``info`` records."""
        return {
            "cache_seconds": self.cache_seconds,
            "seconds": self.seconds,
            "runs": self.runs,
            "reused": self.reused,
            "constant_velocity_mse": self.collected.constant_velocity_mse(),
        }


def run_study(study: Study, recording: PushRecording | None = None) -> Outcome:
    """Make the ``recording`` first if it is absent, build the window cache once (so no run's time
    includes it), train and score what no earlier invocation completed, and read every run's results."""
    start = time.perf_counter()
    record_seconds = None if recording is None else recording.make_if_absent()
    cache_start = time.perf_counter()
    data = open_data(study)
    cache_seconds = time.perf_counter() - cache_start
    runs, reused = run_pending(study)
    collected = collect_runs(study)
    seconds = time.perf_counter() - start
    return Outcome(data, collected, runs, reused, record_seconds, cache_seconds, seconds)


def report_results(out: Path, text: str, results: dict) -> None:
    """Write the report ``text`` to ``<out>/results.md`` and ``results`` to ``<out>/results.json``
    (each replaced whole), then print the report: the script's result on stdout, its summary line
    last."""
    from mmf_rl.eval.report import write_json, write_text

    out.mkdir(parents=True, exist_ok=True)
    write_text(out / "results.md", text)
    write_json(out / "results.json", results)
    print(text, end="")


def run_as_script(main: Callable[[], int]) -> NoReturn:
    """``python benchmarks/X.py``: ``main``'s exit code, with the library's progress messages on stderr
    as ``mmf-rl bench X`` shows them."""
    from mmf_rl.log import configure_logging

    configure_logging()
    sys.exit(main())
