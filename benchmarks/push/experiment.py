"""What the push experiment scripts (``benchmarks/mpc_push.py``, ``benchmarks/bc_push.py``) share: their
common arguments and quick/full budgets, the trainings they build when absent (resumed when
interrupted), a forecaster calibrated before it forecasts, the minutes of each phase, and the
results files."""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

import torch

from benchmarks.push.closed_loop import OUTAGES
from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.configuration import compose_config
from mmf_rl.eval import calibration
from mmf_rl.eval.report import write_json, write_text
from mmf_rl.eval.scale_fit import calibration_in_use
from mmf_rl.models.loading import load_trained_model
from mmf_rl.trainers.training import TrainRunConfig, check_resumable, train

logger = logging.getLogger(__name__)


def add_common_arguments(parser: argparse.ArgumentParser, name: str) -> None:
    """The arguments both push experiments take; ``name`` makes the default work directory
    ``runs/bench_<name>_{quick,full}``. A ``None`` default is filled in by `resolve_budget`."""
    parser.add_argument(
        "--quick", action="store_true", help="the small budget (the script's docstring tabulates both)"
    )
    parser.add_argument(
        "--work",
        type=Path,
        default=None,
        help=f"where what is absent is built (default runs/bench_{name}_{{quick,full}})",
    )
    parser.add_argument("--record-episodes", type=int, default=None)
    parser.add_argument("--workers", type=int, default=2, help="recording processes")
    parser.add_argument(
        "--threads",
        type=int,
        default=2,
        help="torch threads; use 1 on a shared machine (OpenMP threads spin-wait for a thread whose "
        "core is busy: a 2-thread training beside another job runs many times slower than alone, "
        "see docs/results.md)",
    )
    parser.add_argument(
        "--episodes", type=int, default=None, help="episodes per condition (quick 20, full 50)"
    )
    parser.add_argument(
        "--outage",
        nargs="+",
        choices=list(OUTAGES),
        default=None,
        help="how the sensor fails (default: the budget's); the summary's success figures use the first",
    )
    parser.add_argument("--seed", type=int, default=1000, help="episode i is reset with seed + i")
    parser.add_argument("--out", type=Path, default=None, help="where the results go (default: --work)")


def resolve_budget(args: argparse.Namespace, budgets: Mapping[str, Mapping], name: str) -> argparse.Namespace:
    """Fills every argument left ``None`` from the quick or full budget, and the work and output
    directories."""
    mode = "quick" if args.quick else "full"
    for key, value in budgets[mode].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    args.work = args.work or Path(f"runs/bench_{name}_{mode}")
    args.out = args.out or args.work
    return args


def merged_overrides(base: list[str], extra: list[str]) -> list[str]:
    """``base`` Hydra overrides with those of ``extra`` replacing the same keys (Hydra refuses a key
    given twice)."""
    extra_keys = {o.split("=", 1)[0] for o in extra}
    return [o for o in base if o.split("=", 1)[0] not in extra_keys] + list(extra)


def train_or_resume(overrides: list[str]) -> Path:
    """``mmf-rl train`` with ``overrides``; a run that already has checkpoints is resumed, and one
    that had ended is left as it is (its config checked against ``overrides`` as a resume checks
    it: not trained, calibrated or exported again). Returns the run's checkpoints directory."""
    cfg = compose_config("train", overrides)
    run_dir = Path(cfg.run_dir).resolve()
    checkpoints = run_dir / "checkpoints"
    if list_checkpoints(checkpoints):
        cfg.resume = True
        if load_checkpoint(checkpoints, with_trainer_state=False).step >= cfg.trainer.total_steps:
            check_resumable(TrainRunConfig.from_config(cfg))
            logger.info("%s has ended (%d steps): used as it is", run_dir, cfg.trainer.total_steps)
            return checkpoints
    train(cfg)
    return checkpoints


def calibrated_forecaster(
    checkpoints: Path, calibrate: bool = True, data_root: Path | None = None
) -> tuple[tuple, dict | None]:
    """A trained forecaster (`load_trained_model`'s triple) with its forecast scale calibrated per
    presence pattern on its val split, and the fit (`calibration_in_use`).

    A forecaster with a recorded fit (``mmf-rl train`` fits one at the end of a run, by default) is
    used as it is; one without is fitted by ``mmf-rl calibrate``'s own function, which writes the
    factors into its checkpoint (and the run's export), so the next call finds them. ``data_root``:
    where its dataset is, when not where it was trained. ``calibrate=False``: the scale as trained
    (the factors set back to ones in memory, nothing fitted or written) and no fit (``None``).
    """
    loaded = load_trained_model(checkpoints)
    if not calibrate:
        loaded[0].scale_calibration.reset()
        return loaded, None
    if calibration_in_use(loaded[0]) is None:
        overrides = [f"checkpoint={Path(checkpoints).resolve()}"]
        if data_root is not None:
            overrides.append(f"data_root={Path(data_root).resolve()}")
        try:
            fitted = calibration.calibrate(compose_config("calibrate", overrides))
        except ValueError as error:
            raise ValueError(
                f"the forecaster {checkpoints} cannot be calibrated: {error}; or use its scale as trained "
                "(calibrate=False, --no-calibrate)"
            ) from error
        logger.info(
            "forecast scale calibrated on val, written to %s:\n%s", fitted["written"], fitted["table"]
        )
        loaded = load_trained_model(checkpoints)
    return loaded, calibration_in_use(loaded[0])


@contextmanager
def timed_phase(phases: dict[str, float], name: str) -> Iterator[None]:
    """Records the seconds the ``with`` body takes as ``phases[name]``."""
    start = time.perf_counter()
    yield
    phases[name] = time.perf_counter() - start


def run_header(script: str, argv: list[str], started: float, phases: Mapping[str, float]) -> str:
    """The results page's first line: the command, its minutes, threads and each phase's minutes."""
    minutes = (time.perf_counter() - started) / 60
    timing = ", ".join(f"{name} {seconds / 60:.1f} min" for name, seconds in phases.items())
    command = " ".join([script, *argv])
    return f"`{command}` — {minutes:.1f} min on {torch.get_num_threads()} threads ({timing})"


def write_results(args: argparse.Namespace, text: str, results: dict, phases: Mapping[str, float]) -> None:
    """``results.md`` (``text``) and ``results.json`` (``results``, the phases' seconds and the
    arguments) in ``args.out``."""
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "results.md", text)
    payload = {**results, "phases_s": dict(phases), "args": {k: str(v) for k, v in vars(args).items()}}
    write_json(args.out / "results.json", payload)
