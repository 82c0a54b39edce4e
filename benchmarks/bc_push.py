"""Behaviour cloning with and without the forecaster's forecast, in closed loop with a sensor down.

    # quick: builds what it lacks (records, trains the forecaster and the BC policies with small
    # budgets), then plays
    MUJOCO_GL=egl .venv/bin/python benchmarks/bc_push.py --quick
    # full: 1000 recorded episodes, the forecaster's committed budget, 50 episodes per condition
    MUJOCO_GL=egl .venv/bin/python benchmarks/bc_push.py
    # a recording and a forecaster of your own (nothing recorded or trained but the policies)
    MUJOCO_GL=egl .venv/bin/python benchmarks/bc_push.py --data data/push --forecaster runs/push/checkpoints
    # the old setup, for comparison: the forecaster trained on the episodes the policies imitate
    MUJOCO_GL=egl .venv/bin/python benchmarks/bc_push.py --quick --in-sample-forecaster

The question: does a policy that reads the forecaster's forecast of the object's motion stay up when
a sensor fails, better than the same policy without it? Target: the policy with forecasts loses at
most half the success the policy without them loses when the camera is off.

What it builds when absent, under ``--work`` (a re-run reuses the recordings, resumes or skips the
trainings; docs/benchmarks/bc_push.md says what and why, `benchmarks.push.bc_experiment` builds them):

* the policies' recording, by the scripted pusher in one steady style (``WORK/push_steady``), or
  ``--data``;
* the forecaster's own recording (``WORK/push_forecaster``, seed 1) and the forecaster trained on it,
  its scale calibrated on val, or ``--forecaster``;
* per ``--bc-seeds`` seed, one BC policy of each ``--variants``: ``without`` and ``with`` forecasts,
  after ``--dagger`` rounds (default none). An option that changes what a policy is or reads gives it
  runs of its own, and the results a directory of their own (``WORK/<tags>``, unless ``--out``).

=============================================  ===============  ===============================
budget                                         quick            full
=============================================  ===============  ===============================
recorded episodes (policies', forecaster's)    200              1000
forecaster steps x batch                       1000 x 64        3000 x 128 (configs/trainer)
BC steps x batch (each)                        1000 x 64        3000 x 128
BC seeds (each variant)                        0 1              0 1
episodes per condition                         20               50
outage types                                   episode bursts   episode bursts dies
DAgger episodes (per policy, per round)        20               50
=============================================  ===============  ===============================

Every policy plays the same seeded episodes under the same seeded outages (``all`` sensors,
``no-camera (T)`` and ``no-force (T)`` per ``--outage`` type T; ``scripted``, for reference). The
minutes of each phase go to ``results.md`` (measured run times: docs/results.md). Ends with ``summary:
BC success all A%/A2%, no-camera B%/B2%, no-force C%/C2% (without/with forecasts); camera loss
without/with forecasts episode X/Y pts, bursts ... (target with <= without/2: met for K of N outage
types)`` (docs/benchmarks/bc_push.md, "Play and the summary line").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.push.bc_evaluation import VARIANTS, evaluate_bc, summary_line
from benchmarks.push.bc_experiment import (
    ACTION_HEADS,
    DEFAULT_ACTION_CHUNK,
    DEMONSTRATIONS,
    FORECAST_TARGETS,
    TRAIN_OUTAGES,
    RunRefusal,
    forecaster_and_demonstrations,
    replayed_absent_fraction,
    results_tag,
    train_policies,
    training_replay,
)
from benchmarks.push.bc_report import results_page
from benchmarks.push.closed_loop import OUTAGES
from benchmarks.push.dagger import ROUND_SEEDS
from benchmarks.push.experiment import (
    add_common_arguments,
    resolve_budget,
    run_header,
    timed_phase,
    write_results,
)
from benchmarks.push.outage_evaluation import outage_conditions
from mmf_rl.log import configure_logging
from mmf_rl.rl.latched_forecast import RULES

BUDGETS = {
    "quick": {
        "record_episodes": 200,
        "forecaster_steps": 1000,
        "forecaster_batch_size": 64,
        "bc_steps": 1000,
        "bc_batch_size": 64,
        "episodes": 20,
        "outage": ["episode", "bursts"],
        "dagger_episodes": 20,
    },
    "full": {
        "record_episodes": 1000,
        "forecaster_steps": None,
        "forecaster_batch_size": None,
        "bc_steps": 3000,
        "bc_batch_size": 128,
        "episodes": 50,
        "outage": list(OUTAGES),
        "dagger_episodes": 50,
    },
}


def add_forecaster_arguments(parser: argparse.ArgumentParser) -> None:
    """The policies' recording, and the forecaster: given, or trained here on which recording, with
    what budget, and calibrated or not."""
    parser.add_argument("--data", type=Path, default=None, help="a push recording (default: record one)")
    parser.add_argument(
        "--forecaster", type=Path, default=None, help="a trained push forecaster (default: train one)"
    )
    parser.add_argument(
        "--held-out-forecaster",
        action="store_true",
        help="the default, accepted for older commands: the forecaster is trained on a recording of its own "
        "(WORK/push_forecaster, seed 1), never on the episodes the policies imitate",
    )
    parser.add_argument(
        "--in-sample-forecaster",
        action="store_true",
        help="the old setup, for comparison: train the forecaster on the policies' own recording (run "
        "WORK/forecaster), so the policies learn from forecasts of the frames it was trained on",
    )
    parser.add_argument(
        "--forecaster-data",
        type=Path,
        default=None,
        help="a push recording for the held-out forecaster only (default: record one)",
    )
    parser.add_argument("--forecaster-steps", type=int, default=None)
    parser.add_argument("--forecaster-batch-size", type=int, default=None)
    parser.add_argument(
        "--forecaster-override",
        nargs="+",
        default=[],
        help="more `mmf-rl train` overrides for the forecaster (key=value; they win over the above)",
    )
    parser.add_argument(
        "--no-calibrate",
        action="store_true",
        help="the forecasts keep the forecaster's scale as trained (default: calibrated on val per presence "
        "pattern, as mmf-rl calibrate fits it)",
    )


def add_bc_training_arguments(parser: argparse.ArgumentParser) -> None:
    """The BC trainings: budget, seeds and network, the outages the policies train under, and what
    the forecaster forecasts and the ``with`` policies read of it."""
    parser.add_argument("--bc-steps", type=int, default=None)
    parser.add_argument("--bc-batch-size", type=int, default=None)
    parser.add_argument("--bc-seeds", type=int, nargs="+", default=[0, 1], help="trainer seed of each policy")
    parser.add_argument("--bc-d-model", type=int, default=64, help="embedding size per modality")
    parser.add_argument("--bc-hidden", type=int, default=256, help="width of the MLP head")
    parser.add_argument("--bc-image-channels", type=int, nargs="+", default=[16, 32, 32, 32])
    parser.add_argument(
        "--dropout", type=float, default=0.3, help="training outage probability of camera and force"
    )
    parser.add_argument(
        "--forecast-target",
        choices=list(FORECAST_TARGETS),
        default="absolute",
        help="the forecaster trained here forecasts the object's absolute planar position, from partial "
        "windows (absolute, the default), or its position relative to the gripper, from whole windows "
        "(gripper: the earlier default); unused with --forecaster",
    )
    parser.add_argument(
        "--train-outages",
        choices=TRAIN_OUTAGES,
        default="independent",
        help="independent (default): each training sample loses camera and force with probability --dropout; "
        "replayed: each sample's outage is a replay of its episode through the outage processes the run "
        "plays (runs of their own)",
    )
    parser.add_argument(
        "--replay-draws",
        type=int,
        default=2,
        help="with --train-outages replayed: replays of each played condition (default 2)",
    )
    parser.add_argument(
        "--latched-forecast",
        choices=[*RULES, "none"],
        default="precision",
        help="the `with` policies read the latched forecast of this rule and its age (default: precision); "
        "none: the forecast made from the live sensors at each step",
    )
    parser.add_argument(
        "--forecast-steps",
        type=int,
        default=None,
        metavar="N",
        help="the `with` policies read only the first N steps of the forecast (default: all; runs of their "
        "own)",
    )


def add_policy_arguments(parser: argparse.ArgumentParser) -> None:
    """What every policy imitates, what else it reads, how it acts, and which variants are trained."""
    parser.add_argument(
        "--demonstrations",
        choices=DEMONSTRATIONS,
        default=None,
        help="the pusher the recorded policies imitate: steady (the default: one steady style, without "
        "noise, pauses or whims, WORK/push_steady) or drawn (a style drawn per episode, WORK/push); the "
        "forecaster's recording keeps the drawn styles. Not with --data",
    )
    parser.add_argument(
        "--steady-demonstrations",
        action="store_const",
        const="steady",
        dest="demonstrations",
        help="the default, accepted for older commands: --demonstrations steady",
    )
    parser.add_argument(
        "--privileged-object",
        action="store_true",
        help="a diagnostic: the policies also read the object's true planar position (runs of their own)",
    )
    parser.add_argument(
        "--action-chunk",
        type=int,
        default=DEFAULT_ACTION_CHUNK,
        metavar="K",
        help="every BC policy predicts the next K actions and acts with their temporal ensemble (ACT); "
        f"default {DEFAULT_ACTION_CHUNK}; 1: one action per step",
    )
    parser.add_argument(
        "--action-head",
        choices=list(ACTION_HEADS),
        default="mse",
        help="every BC policy's head: mse (regression, default) or gmm (a Gaussian mixture per action step, "
        "acting with its most likely component; runs of their own)",
    )
    parser.add_argument(
        "--variants",
        nargs="+",
        choices=list(VARIANTS),
        default=list(VARIANTS),
        help="the policies trained and played: without and/or with forecasts (default both)",
    )


def add_dagger_arguments(parser: argparse.ArgumentParser) -> None:
    """DAgger rounds before the play, with the scripted pusher as the expert."""
    parser.add_argument(
        "--dagger",
        type=int,
        default=0,
        metavar="ROUNDS",
        help="rounds of DAgger with the scripted pusher as the expert before playing (default 0: none)",
    )
    parser.add_argument(
        "--dagger-episodes",
        type=int,
        default=None,
        help="episodes each policy plays per DAgger round (quick 20, full 50)",
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(parser, "bc")
    add_forecaster_arguments(parser)
    add_bc_training_arguments(parser)
    add_policy_arguments(parser)
    add_dagger_arguments(parser)
    parsed = parser.parse_args(argv)
    check_forecaster_kind(parser, parsed)
    resolve_choices(parser, parsed)
    default_out = parsed.out is None
    args = resolve_budget(parsed, BUDGETS, "bc")
    args.variants = [v for v in VARIANTS if v in args.variants]
    check_forecaster_data(parser, args)
    tag = results_tag(args)
    if default_out and tag:  # never over the results of the ordinary policies in the same work directory
        args.out = args.work / tag
    if args.action_chunk < 1:
        parser.error(f"--action-chunk must be >= 1, found {args.action_chunk}")
    if args.forecast_steps is not None and args.forecast_steps < 1:
        parser.error(f"--forecast-steps must be >= 1, found {args.forecast_steps}")
    if args.train_outages == "replayed" and (args.dagger or args.replay_draws < 1):
        parser.error(
            "--train-outages replayed needs --replay-draws >= 1 and no --dagger rounds (DAgger's episodes "
            f"are not replayed), found --replay-draws {args.replay_draws}, --dagger {args.dagger}"
        )
    if args.dagger < 0 or args.dagger_episodes < 1:
        parser.error(
            f"--dagger must be >= 0 and --dagger-episodes >= 1, found {args.dagger}, {args.dagger_episodes}"
        )
    if max(args.episodes, args.dagger_episodes) > ROUND_SEEDS:
        parser.error(
            f"--episodes and --dagger-episodes must be <= {ROUND_SEEDS}: beyond, DAgger's episodes would "
            "replay the test's"
        )
    return args


def resolve_choices(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Turns the choices given by name into what the run reads: ``args.steady_demonstrations`` (the
    policies' recording is the steady pusher's, recorded here) and ``args.latched_forecast``
    (``None`` for ``none``: not latched); refuses ``--demonstrations`` with ``--data``, whose
    recording is whatever it is."""
    if args.data is not None and args.demonstrations is not None:
        parser.error(
            f"--demonstrations {args.demonstrations} records the policies' recording, but --data gives one; "
            "drop one (record a steady one yourself with mmf-rl record --steady)"
        )
    args.steady_demonstrations = args.data is None and args.demonstrations != "drawn"
    if args.latched_forecast == "none":
        args.latched_forecast = None


def check_forecaster_kind(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Sets ``args.held_out_forecaster``: a forecaster trained here on a recording of its own, the
    default, unless one is given (``--forecaster``) or ``--in-sample-forecaster`` asks for the old
    setup; refuses the options that contradict each other."""
    held_out_asked = args.held_out_forecaster or args.forecaster_data is not None
    if args.in_sample_forecaster and held_out_asked:
        parser.error(
            "--in-sample-forecaster with --held-out-forecaster/--forecaster-data: the forecaster is trained "
            "either on the policies' recording or on one of its own; drop one of them"
        )
    if args.forecaster is not None and (held_out_asked or args.in_sample_forecaster):
        parser.error(
            "--forecaster with --held-out-forecaster/--in-sample-forecaster/--forecaster-data: a given "
            "forecaster is not trained here and the data it was trained on is unknown; drop --forecaster to "
            "train one, or drop the others"
        )
    args.held_out_forecaster = args.forecaster is None and not args.in_sample_forecaster
    if args.held_out_forecaster and any(
        o.split("=", 1)[0].lstrip("+") == "data.root" for o in args.forecaster_override
    ):
        parser.error(
            "--forecaster-override data.root=... with the held-out forecaster (the default): give the "
            "forecaster's recording with --forecaster-data instead, or add --in-sample-forecaster to train "
            "it on the policies' recording"
        )


def check_forecaster_data(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuses a ``--forecaster-data`` that is the policies' recording or no recording at all."""
    if args.forecaster_data is None:
        return
    policies_data = (args.data or args.work / "push").resolve()
    if args.forecaster_data.resolve() == policies_data:
        parser.error(
            f"--forecaster-data {args.forecaster_data} is the policies' recording ({policies_data}): the "
            "forecaster must learn from other episodes; give another recording, or drop --forecaster-data to "
            "record one"
        )
    if not (args.forecaster_data / "meta" / "info.json").is_file():
        parser.error(
            f"--forecaster-data {args.forecaster_data}: not a LeRobot recording (no meta/info.json); give "
            "the directory of a finished push recording (mmf-rl record --out DIR)"
        )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    try:
        run(args, sys.argv[1:] if argv is None else argv)
    except RunRefusal as refusal:  # one line, as argparse's errors, not a traceback
        raise SystemExit(f"bc_push: error: {refusal}") from None


def run(args: argparse.Namespace, argv: list[str]) -> None:
    """Builds what the work directory lacks, plays every policy and writes the results (their header
    quotes ``argv``)."""
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    phases: dict[str, float] = {}
    forecaster, recorded, table, recording = forecaster_and_demonstrations(args, phases)
    replay = training_replay(args, forecaster, recorded, phases)
    policies, errors, dagger_rows = train_policies(args, forecaster, recorded, table, phases, replay)

    # Closed loop: every policy, every condition, the same seeded episodes and outages.
    conditions = outage_conditions(args.outage)
    with timed_phase(phases, "play"):
        rows, raw = evaluate_bc(
            policies, args.bc_seeds, forecaster.loaded, conditions, args.episodes, args.seed
        )

    header = run_header("benchmarks/bc_push.py", argv, started, phases)
    text = results_page(args, header, rows, errors, conditions, forecaster, recorded, dagger_rows)
    results = {
        "rows": rows,
        "episodes": raw,
        "validation_errors": errors,
        "forecaster_calibration": forecaster.calibration,
        "forecaster_recording": forecaster.trained_on,
        "policies_recording": recording,
        "held_out_forecaster": args.held_out_forecaster,
        "dagger": dagger_rows,
        "action_chunk": args.action_chunk,
        "action_head": args.action_head,
        "forecast_steps": args.forecast_steps,
        "train_outages": args.train_outages,
        "replayed_absent_fraction": replayed_absent_fraction(replay),
    }
    write_results(args, text, results, phases)
    print(text)
    print(summary_line(rows, args.outage))


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    main()
