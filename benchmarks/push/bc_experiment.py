"""The push behaviour-cloning experiment of ``benchmarks/bc_push.py`` up to the play: the recordings it
makes or reuses, the forecaster it trains (or is given), calibrates and checks, the BC policies of each
variant and seed after any DAgger rounds, and the names of their run directories.

Every kind of run keeps directories of its own, named by its tags (`policy_tag`, `forecast_tag`), so
a re-run resumes or reuses its own and never mixes kinds; a recording, forecaster or run found in
the work directory that contradicts the run asked for is refused (`RunRefusal`), never overwritten.
The functions read the script's parsed arguments (``args``). docs/benchmarks/bc_push.md says what each piece
builds and why."""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tqdm.auto import tqdm

from benchmarks.push.bc_evaluation import VARIANTS, bc_env, served_forecast
from benchmarks.push.closed_loop import camera_size, sensor_outage, summarise
from benchmarks.push.dagger import (
    EXPERT_NAME,
    demonstration_frames,
    labelled_episodes,
    load_episodes,
    round_seed,
    save_episodes,
)
from benchmarks.push.experiment import calibrated_forecaster, merged_overrides, timed_phase, train_or_resume
from benchmarks.push.gmm_head import GMMPolicy
from benchmarks.push.outage_evaluation import Condition, outage_conditions
from benchmarks.push.replayed_outages import ReplayedOutages
from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.datasets.lerobot_source import open_dataset_metadata
from mmf_rl.datasets.provenance import PROVENANCE_FILE, describe_provenance, read_recording_provenance
from mmf_rl.envs.modality_dropout import ModalityDropout
from mmf_rl.eval.report import write_json
from mmf_rl.record import CAMERA_KEY, RecordConfig, record
from mmf_rl.rl.bc import BCPolicy, EncoderChoice, train_bc, validation_errors
from mmf_rl.rl.demonstrations import Demonstrations, ForecastTable
from mmf_rl.rl.latched_forecast import LatchedForecastTable
from mmf_rl.rl.transforms import HistoryWindow
from mmf_rl.trainers import TrainerConfig, seed_everything

logger = logging.getLogger(__name__)

DROPPABLE = ("image", "force")  # the sensors a training sample may lose
# The policy of each --action-head: the regression of the action (mse), or a Gaussian mixture per step.
ACTION_HEADS = {"mse": BCPolicy, "gmm": GMMPolicy}
TRAIN_OUTAGES = ("independent", "replayed")
# First seed of the outage processes replayed for training; the played conditions use --seed's.
REPLAY_SEED = 7001
# The seed of each recording the experiment makes (under WORK): episode i depends only on (seed, i), so
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
# What the policies imitate: the scripted pusher in one steady style, or in a style drawn per episode.
DEMONSTRATIONS = ("steady", "drawn")
# Chunks of 8 actions: longer than the drawn pusher's longest pause (7 steps), a third of an episode.
DEFAULT_ACTION_CHUNK = 8
# In the run of every `with` policy: the forecaster whose forecasts it learns from.
FORECASTER_RECORD = "forecaster.json"


class RunRefusal(ValueError):
    """A recording or run given or found in the work directory contradicts the run asked for:
    nothing is overwritten; the message names both and the fix."""


def forecaster_run_dir(args) -> Path:
    """The forecaster's run: the held-out one (the default) never resumes the in-sample one, nor one
    of another target."""
    name = "forecaster_held_out" if args.held_out_forecaster else "forecaster"
    return (args.work / f"{name}{target_tag(args)}").resolve()


def target_tag(args) -> str:
    """In the names of the forecasters trained here on the absolute target, and of the runs of the
    ``with`` policies that read them (the gripper-relative target keeps the older, untagged names)."""
    return "_absolute" if args.forecaster is None and args.forecast_target == "absolute" else ""


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


def results_tag(args) -> str:
    """The name of the run's results directory under WORK when ``--out`` is not given (empty: WORK
    itself, the ordinary policies'): a run never writes over the results of another kind."""
    tags = policy_tag(args) + first_steps_tag(args) + forecaster_tag(args) + dagger_tag(args)
    return tags.removeprefix("_")


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
        logger.info("recording %d %sscripted episodes into %s", args.record_episodes, style, data)
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
    logger.info("recording %d episodes (seed %d) for the forecaster into %s", episodes, config.seed, data)
    with timed_phase(phases, "record forecaster data"):
        return record(config)


def training_recording(args, data_config: dict) -> dict:
    """The recording a forecaster of data config ``data_config`` was trained on: its path, the seed
    it was recorded with when the experiment recorded it (else ``None``) and its episode count (``None``
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
    policy_class = ACTION_HEADS[args.action_head]
    if last is not None and last.step >= config.total_steps:
        return policy_class.from_checkpoint(run_dir / "checkpoints")
    seed_everything(seed)  # the same initial encoder weights for both variants
    policy = policy_class.for_demonstrations(
        demonstrations,
        table,
        encoders=EncoderChoice(image_channels=tuple(args.bc_image_channels)),
        privileged_object=args.privileged_object,
        d_model=args.bc_d_model,
        hidden=args.bc_hidden,
        action_chunk=args.action_chunk,
        forecast_steps=args.forecast_steps if variant == "with" else None,
    )
    dagger = f", DAgger round {round_}" if round_ else ""
    steps = config.total_steps
    outages = replay() if replay else None  # its own phase, not the training's
    logger.info("training the BC policy %s forecasts, seed %d%s (%d steps)", variant, seed, dagger, steps)
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
    return policy_class.from_checkpoint(run_dir / "checkpoints")


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
    logger.info("replaying the training episodes through %d outage processes", len(outages))
    with timed_phase(phases, "replay the training outages"):
        with_policies = "with" in args.variants
        forecast = served_forecast(forecaster.loaded, args.latched_forecast) if with_policies else None
        return ReplayedOutages.replay(demonstrations, "train", outages, window, forecast)


def training_replay(
    args, forecaster: Forecaster, demonstrations: Demonstrations, phases: dict[str, float]
) -> Callable[[], ReplayedOutages] | None:
    """With ``--train-outages replayed``: what builds the replayed training outages (`replayed_outages`)
    at its first call, when a policy is trained, and returns the same ones after (a re-run that
    reuses every policy replays nothing). ``None``: the independent dropout."""
    if args.train_outages != "replayed":
        return None
    return functools.cache(lambda: replayed_outages(args, forecaster, demonstrations, phases))


def replayed_absent_fraction(replay: Callable[[], ReplayedOutages] | None) -> dict | None:
    """For the results: what the replays of `training_replay` left absent
    (`ReplayedOutages.absent_fraction`); ``None`` when nothing was replayed."""
    return replay().absent_fraction() if replay and replay.cache_info().currsize else None


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


def train_policies(
    args,
    forecaster: Forecaster,
    recorded: Demonstrations,
    table: ForecastTable,
    phases: dict[str, float],
    replay: Callable[[], ReplayedOutages] | None,
) -> tuple[dict[str, list[BCPolicy]], dict[str, list[dict]], list[dict]]:
    """A policy of each variant (without and with the forecast input) per BC seed, after the DAgger
    rounds (`train_with_dagger`, trained on ``recorded`` and the forecasts ``table``), their offline
    errors on the validation episodes (none when there are none) and the rounds' rows."""
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
    return policies, errors, dagger_rows
