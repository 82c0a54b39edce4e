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

The question: does a policy that reads the forecaster's forecast of the object's
motion stay up when a sensor fails, better than the same policy without it? Target: the policy
with forecasts loses at most half the success the policy without them loses when the camera is
off.

What it builds when absent (under ``--work``; a re-run reuses the recording, resumes or skips
the trainings):

* the policies' recording: scripted pushes without exploration (``mmf-rl record --out WORK/push
  --episodes N --seed 0``): its ``action`` column is what the policies imitate. One found there is
  reused only when its provenance (``meta/mmf_rl_recording.json``) says it was made so, steady or
  drawn as the run asks (see ``--demonstrations``), and it holds the run's episode count (a quick
  run's recording is not a full run's); one without that file (recorded before recordings kept
  it) is reused with a warning. ``results.json`` records the policies' recording
  and its provenance (``policies_recording``);
* the forecaster's recording, ``WORK/push_forecaster``: scripted pushes recorded with seed 1
  (`RECORDING_SEEDS`, so the two recordings share no episode) with the episode count, length and
  image size of the policies' recording (``WORK/push`` or ``--data``); or ``--forecaster-data PATH``,
  a recording of your own for the forecaster only. Why a recording of its own: see "The forecaster
  is held out" below;
* the forecaster: the default push forecaster with the object's planar position as its target
  (`FORECAST_TARGETS`: where the object is, in a frame the policy acts in; the data config's
  default, its displacement from now, mostly restates what the policy is about to do), trained on
  its recording (``mmf-rl train data.root=WORK/push_forecaster``) in the run
  ``WORK/forecaster_held_out_absolute``, with ``--forecaster-steps`` steps of
  ``--forecaster-batch-size``. ``--forecast-target absolute`` (the default): the absolute position,
  the goal's frame, from a forecaster trained on partial windows with burst cuts
  (``data.partial_windows=true loss.step_drop_prob=0.5 loss.step_cut=burst``), so that its latch
  refreshes at every camera frame; ``gripper``: the position relative to the gripper, whole windows
  (the earlier default; its runs keep their untagged names, ``WORK/forecaster_held_out``). The
  ``absolute`` runs are tagged (``..._heldout_absolute_...``). Unused with ``--forecaster``;
* its forecast scale calibrated per presence pattern on its validation split, as ``mmf-rl
  calibrate`` fits it (`mmf_rl.eval.scale_fit`), before it forecasts anything: ``mmf-rl train``
  fits it at the end of the training (``calibrate=true``, its default); a forecaster without a
  recorded fit (one given with ``--forecaster``, or trained with ``calibrate=false``) is fitted
  here with ``mmf-rl calibrate``'s own function, which writes the factors into its checkpoint,
  so a re-run finds them and does not refit. The fit (factors, 90% coverage on val before and
  after, per pattern) goes into ``results.md`` and ``results.json``. ``--no-calibrate``: the
  forecasts use the scale as trained (factors set back to ones in memory; nothing is fitted or
  written), for comparison; its ``with`` policies train in runs of their own (``_uncalibrated``);
* its forecast of every training and validation frame under each training outage
  (`ForecastTable`, computed each run);
* per ``--bc-seeds`` seed, one policy (`BCPolicy`, ``train_bc``) of each ``--variants`` (default
  both): ``without`` forecasts and ``with`` them. Same encoders, sizes, steps, batch, optimiser;
  the same seed gives both the same initial encoder weights, the same batch order and the same
  training outages (the head's first layer is wider by the 2·T·D forecast numbers, plus the age
  with ``--latched-forecast``, so its initial draw differs);
* with ``--dagger ROUNDS`` (default 0: none), per BC seed and round ``r``
  (`mmf_rl.rl.dagger`): the policies of round ``r - 1`` each play ``--dagger-episodes``
  episodes with every sensor (env seeds from ``--seed + 10000·r``, never a test episode's; every
  policy plays the same ones), the scripted pusher labels every state they visited with its
  action, as a function of the state (`MarkovPusher`: the recording's pusher is a state machine
  whose phase, along another's trajectory, no longer matches the state), the labelled frames of
  all are added to that seed's training frames, with their forecasts computed as for the
  recording's, and the policies are trained again from scratch on the union, with the same
  budget and seed. Both variants so see the same data in every round. The episodes are kept
  (``WORK/dagger_markov_seed<S>_round<r>/episodes``, beside the round's policies; with
  ``--latched-forecast``, ``--no-calibrate``, ``--privileged-object``, ``--action-chunk``,
  ``--action-head gmm`` or some ``--variants`` only, the directory's name says so), so a re-run
  does not play them again (nor those of older runs, labelled by the stateful pusher). The
  results report each policy's success on its own DAgger episodes per round; the played
  conditions use the last round's policies. Those are other policies than round 0's, so their
  results go to a directory of their own (``WORK/dagger<ROUNDS>``, after any other tag of the run,
  unless ``--out``), never over round 0's.
  Cost of a round, per BC seed and variant: one more BC training of the first ones' budget
  (training is the phase that dominates a run, so a round takes about as long again as all the
  first trainings) and ``--dagger-episodes`` episodes played (each at the play phase's cost per
  episode), plus their forecasts. The union grows by at most 50 frames per episode
  played; a training's cost does not grow with it (a fixed number of steps).

=============================  ===========  ===============================
budget                         quick        full
=============================  ===========  ===============================
recorded episodes (policies'   200          1000
recording, and forecaster's)
forecaster steps x batch       1000 x 64    3000 x 128 (configs/trainer)
BC steps x batch (each)        1000 x 64    3000 x 128
BC seeds (each variant)        0 1          0 1
episodes per condition         20           50
outage types                   episode      episode bursts dies
                               bursts
DAgger episodes (per policy,   20           50
per round, with --dagger)
=============================  ===========  ===============================

The quick budget is sized from the code's costs (200 recorded episodes, a forecaster training a
quarter the length of the MPC world model's, BC ConvNets with a third of the forecaster's
convolution cost) to take a fraction of the full mode's time. The script prints the minutes of
each phase and writes them to ``results.md``; measured run times are in docs/results.md.

Design (what the policies see, and why):

* Observation: the sensor windows of the forecaster's data config (camera, force, proprio over
  H = 10 steps, `HistoryWindow`), their presence flags, and the goal (FetchPush gives every
  policy its goal; it is not a sensor). Not the object's pose: that is privileged state, which
  the camera, and contact with force and proprioception, must stand in for (but with
  ``--privileged-object``, below).
* Outages in training: each training sample loses the camera and the force sensor
  independently with probability ``--dropout`` (`DEFAULT_DROPOUT`, 0.3), identically for both
  variants; a policy sees the outage through the presence flags and never what an absent
  sensor holds (its encoder is not run on that row). Without it a policy would meet its first
  outage in the test.
* ``--train-outages replayed`` (default ``independent``, the bullet above): each training sample's
  outage is instead one replay of the recorded episode through the outage processes the run plays
  (`mmf_rl.rl.replayed_outages`): every sensor, and each sensor failing each ``--outage`` way,
  ``--replay-draws`` times each with seeds of their own (`REPLAY_SEED`), stepped through the
  policy's `HistoryWindow` and the forecast transform the ``with`` policies read in closed loop.
  What a policy reads in training then follows the process as in the test: a camera in bursts
  leaves the policy's own window without it most of the time, and the latch and its age are
  what the transform serves. Both variants train on the same replays (``--dropout`` is unused);
  their runs are their own (``bc_..._replayed_...``; results in ``WORK/replayed...`` unless
  ``--out``), and one trained on other replays (another ``--outage`` or ``--replay-draws``) is
  refused, never reused or resumed. Not with ``--dagger``.
* The forecast: `ForecastTransform` (``denormalize=False``) on the same live sensors after the
  outage, i.e. the forecaster's own missing-modality inference; the policy reads its ``loc`` and
  ``log(scale)`` (the object's planar position over the next T steps, absolute or relative to the
  gripper, `FORECAST_TARGETS`, and how sure the forecaster is). Training uses the forecaster's forecasts of
  the training frames under the same outage each sample is under, built by the same window rules
  (tests/rl/test_bc.py checks that the offline windows and forecasts equal the transforms' online
  ones).
* ``--latched-forecast RULE`` (default ``precision``; ``none``: the forecast of the live sensors at
  each step): the ``with`` policies read what `LatchedForecastTransform` serves with that rule
  (the last forecast made with the camera, advanced through its outage, and its age), trained on
  the `LatchedForecastTable` of the same forecasts (their runs are
  ``bc_with_latched_<RULE>_forecasts_seed<S>``).
* ``--forecast-steps N`` (default: all T): the ``with`` policies read only the first N steps of
  the forecast (`BCConfig.forecast_steps`): where the object is about to be, not the rest of its
  forecast motion, which restates what the demonstrator was about to do (a policy can copy it,
  and a still forecast then keeps the policy still). Their runs are their own
  (``bc_with_..._first<N>_forecasts_seed<S>``; results in ``WORK/first<N>`` unless ``--out``, after
  any other tag of the run).
* The forecaster is held out: it is trained on a recording of its own, never on the episodes the
  policies imitate. Trained on them, it forecasts the frames the policies learn from far more
  accurately than any frame it meets in closed loop (it overfits its training episodes): the
  policies then learn to rely on forecasts better than any they will get, and a forecast of where
  the object goes gives away the demonstrated action itself. So the two
  stages are fitted on different data, as for any stacked model. The policies train and are
  validated on their own recording, forecast by this forecaster. The ``with`` policies' runs are
  tagged (``bc_with_..._heldout_absolute_forecasts_seed<S>``, ``dagger_markov_..._heldout_absolute_...``;
  results in ``WORK/heldout_absolute`` unless ``--out``, after any other tag of the run; without
  ``_absolute`` for ``--forecast-target gripper``); the ``without`` policies read
  no forecast and are the ordinary ones. ``--held-out-forecaster`` is accepted and changes nothing
  (it was the option's name before it became the default).
* ``--in-sample-forecaster``: the old setup, kept for comparison: the forecaster is trained on the
  policies' own recording (``mmf-rl train data.root=WORK/push``, run ``WORK/forecaster``), so the
  ``with`` policies learn from forecasts of the very frames it was trained on. With ``--forecast-target
  gripper`` its runs keep the untagged names (``bc_with_forecasts_seed<S>``; results in ``WORK``),
  so older work directories resume. Refused with ``--held-out-forecaster`` or ``--forecaster-data``.
* ``--forecaster PATH``: a forecaster of your own; nothing is trained. Its ``with`` policies train
  in runs of their own (``bc_with_..._given_forecasts_seed<S>``, ``dagger_markov_..._given_...``;
  results in ``WORK/given`` unless ``--out``, after any other tag of the run), never in those of the
  forecasters trained here; the ``without`` policies read no forecast and are the ordinary ones.
  The run of every ``with`` policy records the forecaster whose forecasts it learns from
  (``forecaster.json``) and is never reused or resumed with another: a second forecaster given in
  the same ``--work`` stops with an error naming both (give each its own ``--work``). When its
  recorded ``data.root`` is the policies' recording (``--data``, or its own when ``--data`` is not
  given), a warning says the policies learn from in-sample forecasts. Refused with
  ``--held-out-forecaster``, ``--in-sample-forecaster`` or ``--forecaster-data``.
* ``--demonstrations steady`` (the default; ``--steady-demonstrations`` says the same): the
  policies' recording (``WORK/push_steady``, seed 0) is made by the pusher in one steady style
  (`PusherStyle.steady`, ``mmf-rl record --steady``): no action noise, pauses or re-approach
  whims, one speed. ``--demonstrations drawn`` records ``WORK/push`` instead, a style drawn per
  episode: at nearby states its demonstrations hold both "move" and "stay", which a per-step
  regression averages into a stalled action. The forecaster's recording keeps the drawn styles (it
  learns how the object moves, not what to do). Steady runs are tagged (``bc_steady_...``; results
  in ``WORK/steady...`` unless ``--out``). Refused with ``--data``, whose recording is used as it is
  (its runs are untagged).
* ``--privileged-object`` (a diagnostic, not a deployable policy): the policies also read the
  object's true planar position (`BCConfig.privileged_object`), fed like the goal, never removed
  by an outage. If they reach the scripted pusher's success, locating the object from the sensors
  is what limits BC; if not, the imitation itself (data, compounding error, network, budget). Their
  runs are their own (``bc_privileged_...``, ``dagger_privileged_...``; results in
  ``WORK/privileged`` unless ``--out``); ``--variants without`` trains and plays only the policies
  without forecasts (a policy told where the object is has little to gain from them; the other
  variant shows as ``-`` in the tables and the summary line; the camera-loss target is not judged,
  and the summary line counts it met for none of the outage types).
* ``--action-chunk K`` (default 8; 1: one action per step): every policy (both variants,
  privileged ones too) predicts the next K actions and acts with ACT's temporal ensemble of its
  past chunks (`BCConfig.action_chunk`, `mmf_rl.rl.action_chunks`), trained on the next K recorded
  actions of the episode (steps past its end masked out of the loss). With K > 1 its runs are
  tagged (``bc_chunk<K>_...``, ``dagger_markov_chunk<K>_...``; results in ``WORK/chunk<K>`` unless
  ``--out``); the offline errors are those of each chunk's first action, comparable with K = 1.
* ``--action-head gmm`` (default ``mse``): every policy predicts a Gaussian mixture per action
  step (`BCConfig.action_head`, `mmf_rl.rl.gmm_head`, robomimic's BC-GMM), trained by its negative
  log-likelihood, and acts with its most likely component's mean instead of regressing the
  average of the recording's move and stay labels. Composes with ``--action-chunk``. Its runs are
  its own (``bc_gmm_...``, ``dagger_markov_gmm_...``, after any ``chunk<K>``; results in
  ``WORK/gmm`` unless ``--out``); the offline errors are those of the action it takes.

Every policy plays the same seeded episodes (episode ``i`` reset with seed ``--seed + i``;
success is FetchPush's: the object within 5 cm of the goal within the 50-step time limit) under
the same seeded outages (`mmf_rl.rl.closed_loop.OUTAGES`): ``all`` sensors; ``no-camera (T)``
and ``no-force (T)`` for each outage type T (``episode``: off the whole episode; ``bursts``:
2-8 step outages, absent about half the time; ``dies``: off after 1-49 steps). ``scripted``:
the pusher that recorded the data (full state), for reference.

Ends with ``summary: BC success all A%/A2%, no-camera B%/B2%, no-force C%/C2% (without/with
forecasts); camera loss without/with forecasts episode X/Y pts, bursts ... (target with <=
without/2: met for K of N outage types)``: means over BC seeds, success figures for the first
``--outage`` type, camera losses for each; a loss is success with all sensors minus success with
the camera off. The target is judged per outage type because the camera off for a whole episode
leaves nothing that locates the object (see the observation above): both variants are expected
to lose everything there, by construction.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from tqdm.auto import tqdm

from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.cli import configure_logging
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.datasets.lerobot_source import open_dataset_metadata
from mmf_rl.datasets.provenance import PROVENANCE_FILE, describe_provenance, read_recording_provenance
from mmf_rl.envs.modality_dropout import ModalityDropout
from mmf_rl.eval.report import write_json
from mmf_rl.eval.scale_fit import PatternFit, fit_table
from mmf_rl.record import CAMERA_KEY, RecordConfig, record
from mmf_rl.rl import (
    BCPolicy,
    Demonstrations,
    EncoderChoice,
    ForecastTable,
    HistoryWindow,
    train_bc,
    validation_errors,
)
from mmf_rl.rl.bc import ACTION_HEADS
from mmf_rl.rl.bc_evaluation import (
    VARIANTS,
    bc_env,
    camera_loss,
    camera_target_met,
    evaluate_bc,
    figure,
    loss_table,
    served_forecast,
    success_table,
    summary_line,
    validation_table,
)
from mmf_rl.rl.closed_loop import OUTAGES, camera_size, sensor_outage, summarise
from mmf_rl.rl.dagger import (
    EXPERT_NAME,
    ROUND_SEEDS,
    demonstration_frames,
    labelled_episodes,
    load_episodes,
    round_seed,
    save_episodes,
)
from mmf_rl.rl.experiment import (
    add_common_arguments,
    calibrated_forecaster,
    merged_overrides,
    resolve_budget,
    run_header,
    timed_phase,
    train_or_resume,
    write_results,
)
from mmf_rl.rl.latched_forecast import RULES, LatchedForecastTable
from mmf_rl.rl.outage_evaluation import Condition, outage_conditions
from mmf_rl.rl.replayed_outages import ReplayedOutages
from mmf_rl.trainers import TrainerConfig, seed_everything

# Under mmf_rl, so that the library's logging setup (`mmf-rl bench`, or this script's own) shows it.
logger = logging.getLogger("mmf_rl.benchmarks.bc_push")
DROPPABLE = ("image", "force")  # the sensors a training sample may lose
TRAIN_OUTAGES = ("independent", "replayed")
# First seed of the outage processes replayed for training; the played conditions use --seed's.
REPLAY_SEED = 7001
# The seed of each recording the script makes (under WORK): episode i depends only on (seed, i), so
# the two share no episode.
RECORDING_SEEDS = {"push": 0, "push_forecaster": 1}
# The forecaster's target, and how it is trained, per --forecast-target: the object's planar position
# (not the data config's displacement from now) in the goal's frame, learnt from partial windows with
# burst cuts; or relative to the gripper's (observation.state dims 0-1), from whole windows.
FORECAST_TARGETS = {
    "absolute": [
        "data.target.relative=false",
        "data.target.relative_to=null",
        "data.partial_windows=true",
        "loss.step_drop_prob=0.5",
        "loss.step_cut=burst",
    ],
    "gripper": [
        "data.target.relative=false",
        "data.target.relative_to={feature:observation.state,dims:[0,1]}",
    ],
}


class RunRefusal(ValueError):
    """A recording or run given or found in the work directory contradicts the run asked for:
    nothing is overwritten; the message names both and the fix."""


# What the policies imitate: the scripted pusher in one steady style, or in a style drawn per episode.
DEMONSTRATIONS = ("steady", "drawn")
# Chunks of 8 actions: longer than the drawn pusher's longest pause (7 steps), a third of an episode.
DEFAULT_ACTION_CHUNK = 8
# In the run of every `with` policy: the forecaster whose forecasts it learns from.
FORECASTER_RECORD = "forecaster.json"
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


@dataclass
class Forecaster:
    """The trained forecaster (`load_trained_model`'s triple), where it is, and its scale's fit
    (``calibration_in_use``; ``None``: the scale as trained)."""

    checkpoints: Path
    loaded: tuple
    calibration: dict | None
    trained_on: dict  # its training recording: path, seed (None: not recorded here), episodes

    @property
    def stride(self) -> int:
        """The window stride of the forecaster's run."""
        return int(self.loaded[2].get("stride", 1))

    def forecasts(self, args, table: ForecastTable, demonstrations: Demonstrations):
        """What the ``with`` policies read of ``table``: its forecasts, or their latched form."""
        if not args.latched_forecast:
            return table
        return LatchedForecastTable.for_trained(
            table, demonstrations, *self.loaded, rule=args.latched_forecast
        )

    def extended(self, table: ForecastTable, demonstrations: Demonstrations) -> ForecastTable:
        model, stats, _ = self.loaded
        return table.extended(demonstrations, model, stats, stride=self.stride)


def build_recording(args, phases: dict[str, float]) -> Path:
    """The policies' recording, ``WORK/push`` (``WORK/push_steady`` with ``--steady-demonstrations``),
    recorded when absent."""
    steady = args.steady_demonstrations
    data = (args.work / ("push_steady" if steady else "push")).resolve()
    if (data / "meta" / "info.json").is_file():
        check_reused_recording(data, steady)
        check_reused_episodes(data, args.record_episodes)
    else:
        style = "steady " if steady else ""
        print(f"bc_push: recording {args.record_episodes} {style}scripted episodes into {data}")
        with timed_phase(phases, "record"):
            seed = RECORDING_SEEDS["push"]
            config = RecordConfig(
                out=data, episodes=args.record_episodes, workers=args.workers, seed=seed, steady=steady
            )
            record(config)
    return data


def check_reused_episodes(data: Path, episodes: int) -> None:
    """Refuses a policies' recording found under WORK with another episode count than the run's
    budget (e.g. a quick run's, found by a full run in the same ``--work``)."""
    found = open_dataset_metadata(data, RecordConfig.repo_id).total_episodes
    if found != episodes:
        raise RunRefusal(
            f"{data} holds {found} episodes, this run's budget is {episodes} (--record-episodes, or the "
            f"mode's): remove it to record {episodes}, give --record-episodes {found} to use it as it is, "
            "or use another --work"
        )


def check_reused_recording(data: Path, steady: bool) -> None:
    """Refuses a policies' recording found under WORK whose provenance says it is not what this run
    would record (the scripted pusher, steady or drawn as ``steady`` says, seed 0); one without
    provenance (recorded before recordings said how they were made) is reused with a warning."""
    provenance = read_recording_provenance(data)
    style = "steady" if steady else "a style drawn per episode"
    expected = f"demonstrations by the scripted pusher ({style}) with seed {RECORDING_SEEDS['push']}"
    if provenance is None:
        logger.warning(
            "%s has no %s: reused, but whether it holds %s cannot be checked",
            data,
            PROVENANCE_FILE,
            expected,
        )
        return
    wanted = {"steady": steady, "seed": RECORDING_SEEDS["push"], "policy": None}
    if any(provenance.get(key, "absent") != value for key, value in wanted.items()):
        raise RunRefusal(
            f"{data / PROVENANCE_FILE}: {describe_provenance(provenance)}; this run expects {expected}: "
            f"remove {data} to record it again, or give another --work"
        )


def build_forecaster_recording(args, policies_data: Path, phases: dict[str, float]) -> Path:
    """The held-out forecaster's recording: ``--forecaster-data``, or ``WORK/push_forecaster``, scripted
    pushes of another seed with the episode count, length and image size of ``policies_data``
    (recorded when absent)."""
    if args.forecaster_data is not None:
        return args.forecaster_data.resolve()
    data = (args.work / "push_forecaster").resolve()
    meta = open_dataset_metadata(policies_data, RecordConfig.repo_id)
    episodes = meta.total_episodes
    if CAMERA_KEY not in meta.features:
        raise RunRefusal(
            f"{policies_data} has no camera feature {CAMERA_KEY}: this script cannot record one like it for "
            "the forecaster; give the forecaster's recording with --forecaster-data"
        )
    if (data / "meta" / "info.json").is_file():
        found = open_dataset_metadata(data, RecordConfig.repo_id).total_episodes
        if found != episodes:
            raise RunRefusal(
                f"{data} holds {found} episodes, the policies' recording {policies_data} {episodes}: the "
                "forecaster's recording must match it; remove it, or use another --work"
            )
        return data
    config = RecordConfig(
        out=data,
        episodes=episodes,
        workers=args.workers,
        seed=RECORDING_SEEDS["push_forecaster"],
        image_size=meta.features[CAMERA_KEY]["shape"][0],
        steps=meta.total_frames // episodes,
    )
    print(f"bc_push: recording {episodes} episodes (seed {config.seed}) for the forecaster into {data}")
    with timed_phase(phases, "record forecaster data"):
        return record(config)


def training_recording(args, data_config: dict) -> dict:
    """The recording a forecaster of data config ``data_config`` was trained on: its path, the seed
    it was recorded with when this script recorded it (else ``None``) and its episode count (``None``
    when it is not on this machine)."""
    root = data_config.get("root")
    if root is None:
        return {"path": data_config.get("repo_id"), "seed": None, "episodes": None}
    root = Path(root).resolve()
    seeds = {(args.work / name).resolve(): seed for name, seed in RECORDING_SEEDS.items()}
    episodes = None
    if (root / "meta" / "info.json").is_file():
        episodes = open_dataset_metadata(root, RecordConfig.repo_id).total_episodes
    return {"path": str(root), "seed": seeds.get(root), "episodes": episodes}


def forecaster_run_dir(args) -> Path:
    """The forecaster's run: the held-out one (the default) never resumes the in-sample one, nor one
    of another target."""
    name = "forecaster_held_out" if args.held_out_forecaster else "forecaster"
    return (args.work / f"{name}{target_tag(args)}").resolve()


def target_tag(args) -> str:
    """In the names of the forecasters trained here on the absolute target, and of the runs of the
    ``with`` policies that read them (the gripper-relative target keeps the older, untagged names)."""
    return "_absolute" if args.forecaster is None and args.forecast_target == "absolute" else ""


def build_forecaster(args, data: Path, phases: dict[str, float]) -> Path:
    """The default push forecaster trained on ``data`` (resumed or skipped when already there)."""
    overrides = [
        "name=bc_forecaster",
        f"run_dir={forecaster_run_dir(args)}",
        f"data.root={data}",
        *FORECAST_TARGETS[args.forecast_target],
        "trainer.seed=0",
        "trainer.progress_bar=false",
    ]
    if args.forecaster_steps is not None:
        overrides.append(f"trainer.total_steps={args.forecaster_steps}")
    if args.forecaster_batch_size is not None:
        overrides.append(f"trainer.batch_size={args.forecaster_batch_size}")
    with timed_phase(phases, "train forecaster"):
        return train_or_resume(merged_overrides(overrides, args.forecaster_override))


def bc_trainer_config(args, seed: int) -> TrainerConfig:
    steps = args.bc_steps
    return TrainerConfig(
        total_steps=steps,
        batch_size=args.bc_batch_size,
        lr=1e-3,
        warmup_steps=min(50, max(1, steps // 10)),
        eval_every=min(500, steps),
        checkpoint_every=min(500, steps),
        seed=seed,
        progress_bar=False,
    )


def forecast_tag(args) -> str:
    """What the forecasts the ``with`` policies read are, in their run directories' names."""
    latched = f"_latched_{args.latched_forecast}" if args.latched_forecast else ""
    uncalibrated = "_uncalibrated" if args.no_calibrate else ""
    return latched + uncalibrated + first_steps_tag(args) + forecaster_tag(args)


def first_steps_tag(args) -> str:
    """In the names of the runs of ``with`` policies that read only the forecast's first steps."""
    return f"_first{args.forecast_steps}" if args.forecast_steps else ""


def forecaster_tag(args) -> str:
    """In the names of the runs of ``with`` policies: whose forecasts they read. A forecaster trained
    here on its own recording (the default) or given with ``--forecaster``; none for the in-sample
    one, so older work directories resume."""
    if args.held_out_forecaster:
        return "_heldout" + target_tag(args)
    return "_given" if args.forecaster is not None else target_tag(args)


def steady_tag(args) -> str:
    """In the names of the runs of policies that imitate the steady pusher's recording."""
    return "_steady" if args.steady_demonstrations else ""


def privileged_tag(args) -> str:
    """In the names of the runs of policies told the object's position: they never mix with the others."""
    return "_privileged" if args.privileged_object else ""


def chunk_tag(args) -> str:
    """In the names of the runs of action-chunk policies (k > 1): a run never resumes another k's."""
    return f"_chunk{args.action_chunk}" if args.action_chunk > 1 else ""


def head_tag(args) -> str:
    """In the names of the runs of mixture-head policies: a run never resumes a regression's."""
    return "_gmm" if args.action_head == "gmm" else ""


def replay_tag(args) -> str:
    """In the names of the runs of policies trained on replayed outages: they never mix with the others."""
    return "_replayed" if args.train_outages == "replayed" else ""


def policy_tag(args) -> str:
    """What kind every policy of the run is, in its runs' names (empty for the ordinary ones, so the
    runs of older versions stay valid)."""
    return steady_tag(args) + privileged_tag(args) + chunk_tag(args) + head_tag(args) + replay_tag(args)


def dagger_tag(args) -> str:
    """In the name of the results directory of a run whose policies went through DAgger rounds: they
    are other policies than those of round 0, whose results stay where they are."""
    return f"_dagger{args.dagger}" if args.dagger else ""


def dagger_dir(args, seed: int, round_: int) -> Path:
    """Round ``round_``'s episodes and policies of BC seed ``seed``: they depend on the policies of
    every variant played, so on the forecasts the ``with`` ones read."""
    played = "" if tuple(args.variants) == VARIANTS else "_" + "_".join(args.variants)
    tags = f"_{EXPERT_NAME}{policy_tag(args)}{played}{forecast_tag(args)}"
    return args.work / f"dagger{tags}_seed{seed}_round{round_}"


def policy_run_dir(args, variant: str, seed: int, round_: int) -> Path:
    if round_ == 0:
        tag = forecast_tag(args) if variant == "with" else ""
        return args.work / f"bc{policy_tag(args)}_{variant}{tag}_forecasts_seed{seed}"
    return dagger_dir(args, seed, round_) / f"bc_{variant}_forecasts"


def record_or_check_forecaster(run_dir: Path, forecaster: Path, new_run: bool) -> None:
    """Records in the new ``with`` run ``run_dir`` the forecaster (its checkpoints) whose forecasts it
    learns from; refuses an existing run recorded with another, which reused or resumed would mix two
    forecasters' forecasts. A run without a record (trained before runs kept one) is not checked."""
    path = run_dir / FORECASTER_RECORD
    given = str(forecaster.resolve())
    if new_run:
        run_dir.mkdir(parents=True, exist_ok=True)
        write_json(path, {"checkpoints": given})
    elif path.is_file() and (trained_on := json.loads(path.read_text())["checkpoints"]) != given:
        raise RunRefusal(
            f"{run_dir} holds a policy trained on the forecasts of the forecaster {trained_on}, not of the "
            f"one given now, {given}: use another --work for this forecaster, or remove {run_dir} and the "
            f"DAgger rounds after it to train them on its forecasts (the same forecaster moved: write its "
            f"new path into {path})"
        )


def build_policy(
    args, variant: str, seed: int, round_: int, demonstrations, forecasts, forecaster: Path, phases, replay
) -> BCPolicy:
    """The ``variant`` policy of BC seed ``seed`` trained on ``demonstrations`` (those of DAgger round
    ``round_``; 0: the recording's), a ``with`` one on ``forecasts`` of the forecaster at ``forecaster``:
    trained under ``args.work`` unless already done. ``replay``: builds the replayed training outages
    (`replayed_outages`) when called; ``None``: the independent dropout."""
    run_dir = policy_run_dir(args, variant, seed, round_)
    config = bc_trainer_config(args, seed)
    table = forecasts if variant == "with" else None
    checkpoints = list_checkpoints(run_dir / "checkpoints")
    last = load_checkpoint(checkpoints[-1], with_trainer_state=False) if checkpoints else None
    if variant == "with":
        record_or_check_forecaster(run_dir, forecaster, new_run=not checkpoints)
    if last is not None and replay:
        check_replayed_run(args, run_dir, last.meta)
    if last is not None and last.step >= config.total_steps:
        return BCPolicy.from_checkpoint(run_dir / "checkpoints")
    seed_everything(seed)  # the same initial encoder weights for both variants
    policy = BCPolicy.for_demonstrations(
        demonstrations,
        table,
        encoders=EncoderChoice(image_channels=tuple(args.bc_image_channels)),
        privileged_object=args.privileged_object,
        d_model=args.bc_d_model,
        hidden=args.bc_hidden,
        action_chunk=args.action_chunk,
        action_head=args.action_head,
        forecast_steps=args.forecast_steps if variant == "with" else None,
    )
    dagger = f", DAgger round {round_}" if round_ else ""
    steps = config.total_steps
    outages = replay() if replay else None  # its own phase, not the training's
    print(f"bc_push: training the BC policy {variant} forecasts, seed {seed}{dagger} ({steps} steps)")
    with timed_phase(phases, f"train BC {variant} seed {seed}{dagger}"):
        train_bc(
            policy,
            demonstrations,
            config,
            dropout={} if replay else dict.fromkeys(DROPPABLE, args.dropout),
            forecasts=table,
            outages=outages,
            run_dir=run_dir,
            resume=bool(checkpoints),
        )
    return BCPolicy.from_checkpoint(run_dir / "checkpoints")


def dagger_episodes(args, seed: int, round_: int, policies: dict[str, BCPolicy], forecaster, specs, phases):
    """Round ``round_``'s labelled episodes of the policies of BC seed ``seed`` (read back when a
    run already played them) and one row per variant: its success on its own episodes."""
    directory = dagger_dir(args, seed, round_) / "episodes"
    saved = load_episodes(directory)
    if saved is None:
        image_size = camera_size(forecaster.loaded[0].config.modalities)
        first = round_seed(args.seed, round_)
        episodes, results = [], []
        with timed_phase(phases, f"DAgger seed {seed} round {round_} episodes"):
            for variant in args.variants:
                policy = policies[variant].eval()
                env = bc_env(policy, forecaster.loaded, image_size, Condition("all", None, None), first)
                played = labelled_episodes(env, policy, args.dagger_episodes, first)
                desc = f"[seed {seed}] DAgger round {round_}, BC {variant} forecasts"
                try:
                    for rollout, result in tqdm(
                        played, desc=desc, total=args.dagger_episodes, unit="episode"
                    ):
                        episodes.append(demonstration_frames(rollout, specs))
                        results.append({**result, "variant": variant})
                finally:
                    env.close()
        save_episodes(directory, episodes, results)
    else:
        episodes, results = saved
    rows = []
    for variant in args.variants:
        own = [r for r in results if r["variant"] == variant]
        rows.append(
            {
                "bc_seed": seed,
                "round": round_,
                "variant": variant,
                "episodes": len(own),
                "success": summarise(own)["success"],
                "frames_added": sum(r["steps"] for r in own),
            }
        )
    return episodes, rows


def replay_processes(args) -> list[tuple[str, ModalityDropout | None]]:
    """``(label, outage process)`` of each replay: every condition the run plays, ``--replay-draws``
    times each with seeds from `REPLAY_SEED` (the labels are what a policy trained on them records)."""
    processes = []
    for draw in range(args.replay_draws):
        for i, condition in enumerate(outage_conditions(args.outage)):
            seed = REPLAY_SEED + 100 * draw + i
            failing = sensor_outage(condition.sensor, condition.outage, seed) if condition.sensor else None
            processes.append((condition.label, failing))
    return processes


def check_replayed_run(args, run_dir: Path, meta: dict) -> None:
    """Refuses to reuse or resume the policy of ``run_dir`` (its checkpoint's ``meta``) when it was
    trained on other replays than this run's (another ``--outage`` or ``--replay-draws``): the results
    would say it was trained on these."""
    trained_on, replayed = meta.get("replayed_outages"), [label for label, _ in replay_processes(args)]
    if trained_on != replayed:
        raise RunRefusal(
            f"{run_dir} holds a policy trained on the outages replayed through {trained_on}, this run "
            f"replays {replayed} (--outage, --replay-draws): use another --work for this run, or remove "
            f"{run_dir} to train the policy on its replays"
        )


def replayed_outages(args, forecaster: Forecaster, demonstrations: Demonstrations, phases) -> ReplayedOutages:
    """The training split replayed through `replay_processes`, with the ``with`` policies' window and
    forecast transform (no forecast when no ``with`` policy is trained: ``--variants without``)."""
    outages = replay_processes(args)
    window = HistoryWindow(
        demonstrations.specs, demonstrations.normalizer.stats, demonstrations.history, demonstrations.stride
    )
    print(f"bc_push: replaying the training episodes through {len(outages)} outage processes")
    with timed_phase(phases, "replay the training outages"):
        with_policies = "with" in args.variants
        forecast = served_forecast(forecaster.loaded, args.latched_forecast) if with_policies else None
        return ReplayedOutages.replay(demonstrations, "train", outages, window, forecast)


def train_with_dagger(args, seed: int, forecaster: Forecaster, demonstrations, table, phases, replay):
    """The policies of BC seed ``seed`` (``--variants``) after ``--dagger`` rounds (none: trained on
    the recording), the demonstrations of their last round with what the ``with`` policies read of
    them, and the rounds' rows. ``replay``: as `build_policy`'s (not with DAgger rounds)."""
    forecasts = forecaster.forecasts(args, table, demonstrations)
    policies = {
        v: build_policy(args, v, seed, 0, demonstrations, forecasts, forecaster.checkpoints, phases, replay)
        for v in args.variants
    }
    rows = []
    for round_ in range(1, args.dagger + 1):
        episodes, played = dagger_episodes(
            args, seed, round_, policies, forecaster, demonstrations.specs, phases
        )
        demonstrations = demonstrations.with_episodes(episodes)
        with timed_phase(phases, f"forecast DAgger seed {seed} round {round_}"):
            table = forecaster.extended(table, demonstrations)
        forecasts = forecaster.forecasts(args, table, demonstrations)
        policies = {
            v: build_policy(
                args, v, seed, round_, demonstrations, forecasts, forecaster.checkpoints, phases, None
            )
            for v in args.variants
        }
        trained_on = len(demonstrations.split_frames["train"])
        rows += [{**row, "frames_trained_on": trained_on} for row in played]
    return policies, demonstrations, forecasts, rows


def add_training_arguments(parser: argparse.ArgumentParser) -> None:
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
    add_training_arguments(parser)
    parsed = parser.parse_args(argv)
    check_forecaster_kind(parser, parsed)
    resolve_choices(parser, parsed)
    default_out = parsed.out is None
    args = resolve_budget(parsed, BUDGETS, "bc")
    args.variants = [v for v in VARIANTS if v in args.variants]
    check_forecaster_data(parser, args)
    tags = policy_tag(args) + first_steps_tag(args) + forecaster_tag(args) + dagger_tag(args)
    if default_out and tags:  # never over the results of the ordinary policies in the same work directory
        args.out = args.work / tags.removeprefix("_")
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


def forecaster_and_demonstrations(args, phases: dict[str, float]):
    """The forecaster (built when not given, calibrated), the demonstrations, the forecaster's
    forecasts of them (a `ForecastTable`) and the record of their recording (`policies_recording`)."""
    data = args.data.resolve() if args.data else None  # the policies' recording
    if args.forecaster is not None:
        checkpoints = args.forecaster
    else:
        data = data or build_recording(args, phases)
        trained_on = build_forecaster_recording(args, data, phases) if args.held_out_forecaster else data
        checkpoints = build_forecaster(args, trained_on, phases)
    # Where the forecaster's val split is when not where its config points: a held-out forecaster
    # was trained here, on its own recording, and is calibrated on that.
    calibration_data = None if args.held_out_forecaster else args.data
    with timed_phase(phases, "calibrate forecaster"):
        loaded, calibration = calibrated_forecaster(checkpoints, not args.no_calibrate, calibration_data)
    forecaster = Forecaster(checkpoints, loaded, calibration, training_recording(args, loaded[2]))
    if args.forecaster is not None:
        warn_of_in_sample_forecasts(forecaster, data)
    model, stats, data_config = forecaster.loaded
    if data is not None:  # the policies' recording, wherever the forecaster was trained
        data_config = {**data_config, "root": str(data)}
    with timed_phase(phases, "forecast the demonstrations"):
        demonstrations = Demonstrations(WindowDataset(DataConfig.from_dict(data_config)))
        table = ForecastTable.for_trained(demonstrations, model, stats, data_config, DROPPABLE)
    return forecaster, demonstrations, table, policies_recording(data_config)


def policies_recording(data_config: dict) -> dict:
    """The results' record of the recording the policies imitate: its path (or hub ``repo_id``) and
    how `mmf-rl record` made it (``None``: not said, e.g. an older recording)."""
    root = data_config.get("root")
    provenance = read_recording_provenance(root) if root is not None else None
    return {"path": root if root is not None else data_config.get("repo_id"), "provenance": provenance}


def warn_of_in_sample_forecasts(forecaster: Forecaster, policies_data: Path | None) -> None:
    """A warning when a given forecaster was trained on the policies' recording (``policies_data``;
    ``None``: the policies read the forecaster's own recording)."""
    trained_on = forecaster.trained_on["path"]
    if policies_data is not None and trained_on != str(policies_data):
        return
    logger.warning(
        "the forecaster %s was trained on the policies' recording %s: the policies learn from its "
        "forecasts of the very frames it was trained on, more accurate than any it makes in closed loop; "
        "see docs/results.md, 'BC with a held-out forecaster'. Give --data a recording it was not trained "
        "on, or drop --forecaster to train a held-out one",
        forecaster.checkpoints,
        trained_on,
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
    replay = None  # built once, when a policy is trained on replayed outages
    if args.train_outages == "replayed":
        replay = functools.cache(lambda: replayed_outages(args, forecaster, recorded, phases))

    # A policy of each variant (without and with the forecast input) per BC seed, after the DAgger
    # rounds; their offline errors.
    policies: dict[str, list[BCPolicy]] = {v: [] for v in args.variants}
    errors: dict[str, list[dict]] = {v: [] for v in args.variants}
    dagger_rows = []
    for seed in args.bc_seeds:
        trained, demonstrations, forecasts, rows = train_with_dagger(
            args, seed, forecaster, recorded, table, phases, replay
        )
        dagger_rows += rows
        for variant in args.variants:
            policies[variant].append(trained[variant])
            if len(demonstrations.split_frames["val"]):
                read = forecasts if variant == "with" else None
                errors[variant].append(
                    validation_errors(trained[variant], demonstrations, "val", DROPPABLE, read)
                )

    # Closed loop: every policy, every condition, the same seeded episodes and outages.
    conditions = outage_conditions(args.outage)
    with timed_phase(phases, "play"):
        rows, raw = evaluate_bc(
            policies, args.bc_seeds, forecaster.loaded, conditions, args.episodes, args.seed
        )

    header = run_header("benchmarks/bc_push.py", argv, started, phases)
    budget = f"{budget_line(args, forecaster, recorded)}\n\n{recording_line(forecaster.trained_on)}"
    extra = calibration_section(forecaster.calibration) + dagger_section(dagger_rows)
    text = report(rows, errors, conditions, args.outage, f"{header}\n\n{budget}", args.privileged_object)
    text += extra
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
        "replayed_absent_fraction": replay().absent_fraction()
        if replay and replay.cache_info().currsize
        else None,
    }
    write_results(args, text, results, phases)
    print(text)
    print(summary_line(rows, args.outage))


def budget_line(args, forecaster: Forecaster, recorded: Demonstrations) -> str:
    """The run's budget and what its policies read, for the results page."""
    return (
        f"{args.episodes} episodes per condition, outages {' '.join(args.outage)}, BC seeds {args.bc_seeds}, "
        f"{args.bc_steps} BC steps x {args.bc_batch_size}, {training_outages_phrase(args)}; "
        + ("demonstrations by the steady pusher; " if args.steady_demonstrations else "")
        + (f"latched forecasts (rule {args.latched_forecast}); " if args.latched_forecast else "")
        + (f"action chunks of {args.action_chunk}, temporal ensembling; " if args.action_chunk > 1 else "")
        + (
            f"the `with` policies read the first {args.forecast_steps} forecast steps; "
            if args.forecast_steps
            else ""
        )
        + ("Gaussian-mixture action head (most likely component); " if args.action_head == "gmm" else "")
        + (
            f"policies {' and '.join(args.variants)} forecasts only; "
            if args.variants != list(VARIANTS)
            else ""
        )
        + (
            f"DAgger {args.dagger} rounds of {args.dagger_episodes} episodes per policy; "
            if args.dagger
            else ""
        )
        + (held_out_phrase(forecaster.trained_on) if args.held_out_forecaster else "")
        + ("forecaster trained on the policies' recording (in-sample); " if args.in_sample_forecaster else "")
        + "forecaster "
        f"`{forecaster.checkpoints}`; {len(recorded.split_frames['train'])} recorded training frames"
    )


def training_outages_phrase(args) -> str:
    """The budget line's word on the training outages."""
    if args.train_outages == "replayed":
        played = len(outage_conditions(args.outage))
        return f"training outages replayed through the {played} played conditions x {args.replay_draws} draws"
    return f"training dropout {args.dropout}"


def held_out_phrase(trained_on: dict) -> str:
    """The budget line's word on a held-out forecaster: the seed of its recording when recorded here."""
    own = f"seed {trained_on['seed']}" if trained_on["seed"] is not None else f"`{trained_on['path']}`"
    return f"forecaster trained on its own recording ({own}); "


def recording_line(trained_on: dict) -> str:
    """The results page's line on the recording the forecaster was trained on."""
    seed = "not recorded by this script"
    if trained_on["seed"] is not None:
        seed = f"recorded here with seed {trained_on['seed']}"
    episodes = "episodes unknown" if trained_on["episodes"] is None else f"{trained_on['episodes']} episodes"
    return f"The forecaster was trained on the recording `{trained_on['path']}` ({seed}, {episodes})."


def calibration_section(record: dict | None) -> str:
    """The forecaster's scale calibration: its fit per presence pattern, or that there is none."""
    if record is None:
        return "\nForecast scale: as trained, not calibrated (--no-calibrate).\n"
    if record["split"] is None:
        return f"\nForecast scale: factors {record['factors']} (their fit is not recorded with the model).\n"
    fits = [PatternFit(**fit) for fit in record["patterns"]]
    return (
        f"\nForecast scale: calibrated per presence pattern on the {record['split']} split before any "
        f"forecast (as `mmf-rl calibrate`, min_windows={record['min_windows']}):\n\n"
        f"{fit_table(fits, record['split'])}\n"
    )


def dagger_section(rows: list[dict]) -> str:
    """Per BC seed, round and variant: the policy's success on its own DAgger episodes (those of the
    policy of the round before) and the frames the round's policies are trained on."""
    if not rows:
        return ""
    lines = [
        "| BC seed | round | policy playing | episodes | success % (own episodes) | frames added | "
        "training frames after |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['bc_seed']} | {r['round']} | BC {r['variant']} forecasts of round {r['round'] - 1} | "
            f"{r['episodes']} | {r['success']:.0f} | {r['frames_added']} | {r['frames_trained_on']} |"
        )
    return (
        "\nDAgger (expert: the scripted pusher as a function of the state; every sensor):\n\n"
        + "\n".join(lines)
        + "\n"
    )


def report(rows: dict, errors: dict, conditions: list, outages: list[str], run: str, privileged: bool) -> str:
    """The results page: the run and its budget (``privileged``: the policies were told the object's
    position), the success and loss tables, the offline errors and the camera-loss target."""
    loss = camera_loss(rows, outages)
    met = camera_target_met(loss)
    title = "# Behaviour cloning with and without forecasts on the multimodal push task"
    if privileged:
        title += (
            "\n\nPrivileged policies (a diagnostic, not deployable): every BC policy here also reads the "
            "object's true planar position."
        )
    target = "; ".join(
        f"{outage} {'met' if met[outage] else 'not met'} ({figure(lost[1])} vs {figure(lost[0])} pts)"
        for outage, lost in loss.items()
    )
    if len(errors) < len(VARIANTS):
        target = f"not judged: only the policies {' and '.join(errors)} forecasts were played"
    return (
        f"{title}\n\n{run}\n\n"
        f"{success_table(rows)}\n\nSuccess lost against all sensors:\n\n{loss_table(rows, conditions)}\n\n"
        "Offline: mean squared action error on the validation episodes, with each sensor subset removed "
        f"(mean over BC seeds):\n\n{validation_table(errors)}\n\n"
        f"Camera-loss target (success lost with forecasts <= half of that lost without): {target}\n"
    )


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    main()
