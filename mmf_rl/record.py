"""`mmf-rl record`: record pushes in `MultimodalPushEnv` as a LeRobot v3.0 dataset, and merge recordings.

    mmf-rl record --out data/push --episodes 200 --workers 2 --seed 0 --image-size 64 --steps 50
    mmf-rl record --out data/round1 --episodes 100 --policy runs/world_model/checkpoints --exploration 0.1
    mmf-rl record --merge data/push data/round1 --out data/push_round1

Episode ``i`` depends only on ``(seed, i)``: worker ``k`` records a contiguous block of episodes
into its own shard, and lerobot's `aggregate_datasets` concatenates the shards in order. All of it
happens in a hidden temporary directory beside ``--out`` (``.NAME.partial-PID-HOST-*``), renamed
into place at the end, so an interrupted or failed recording never leaves a partial dataset at
``--out``. A recording that was killed outright (SIGKILL, power loss) cannot clean up: the next
recording beside the same ``--out`` removes the temporary directories whose process is gone.

The dataset says how it was made: ``meta/mmf_rl_recording.json`` (`recording_provenance`) holds
the options that define its data (not ``--workers`` or ``--overwrite``), the policy that acted and
the mmf-rl version; a merge's lists those of its sources, in order. It is written before the
rename, so it is there exactly when the dataset is. `mmf_rl.datasets.provenance` reads it back;
`mmf-rl inspect` shows it.

Features (float32 vectors carry per-dimension ``names``):

===================================  =========  ================================================
``observation.images.front``         video      RGB camera, ``[h, w, 3]``
``observation.front_camera_valid``   bool [1]   true when the frame is fresh, false frozen/black
``observation.force``                [6]        gripper->object force/torque, world frame, summed
                                                over the physics sub-steps; NaN during a dropout
``observation.state``                [17]       proprioception (gripper position/velocity,
                                                fingers, arm joints)
``observation.object_pose``          [7]        object position and quaternion (the target)
``observation.goal``                 [3]        goal position
``action``                           [4]        FetchPush action (dx, dy, dz, gripper)
===================================  =========  ================================================

With ``--exploration P``, the pusher makes random-move bursts (`ScriptedPusher`): the data a
world model needs to learn what the actions do, not what the pusher tends to do. With
``--steady``, it pushes in one steady style (no noise, pauses or whims): demonstrations for
imitation, where the drawn styles' "move" and "stay" at nearby states would be averaged.

Another agent can act instead of the scripted pusher (``RecordConfig.policy``; ``--policy
CHECKPOINT`` in `mmf-rl record`: MPC with that world model, `mmf_rl.rl.PushMPCAgent`), with the
same ``--exploration`` bursts on top (`mmf_rl.envs.scripted.ExploringActor`). The recorder sits
below the models and never imports one: the policy comes as a picklable factory, called once in
each worker to build that worker's own agent. The features are the same either way, so
recordings of both kinds merge (`merge_recordings`, ``--merge``: lerobot's
`aggregate_datasets`) into one dataset that trains with the same data config: PETS-style data
aggregation (record with the current agent, retrain on the union, repeat).

With ``--faults``, sensor outages are written into the data (`SensorFaults`); without it the
validity feature is all true and no value is NaN, and the two recordings are otherwise identical.
lerobot's statistics are not NaN-aware: a recording with force dropouts has NaN force entries in
``meta/stats.json``, so normalise force from the valid frames instead.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

import mmf_rl
from mmf_rl.datasets.provenance import PROVENANCE_FILE, read_recording_provenance
from mmf_rl.envs.push import (
    ACTION_NAMES,
    FORCE_NAMES,
    GOAL_NAMES,
    OBJECT_POSE_NAMES,
    PROPRIO_NAMES,
    MultimodalPushEnv,
    camera_names,
)
from mmf_rl.envs.scripted import Actor, rollout
from mmf_rl.shards import ShardError, join_shards, run_shards
from mmf_rl.temp_dirs import StagingError, staging_dir

PROG = "mmf-rl record"
TASK = "Push the block to the red target."
ROBOT_TYPE = "fetch"
CAMERA_KEY = "observation.images.front"
# lerobot 0.4.4 treats every feature whose name contains "image" as a camera when it aggregates
# stats, so the camera's validity flag cannot live under "observation.images.".
CAMERA_VALID_KEY = "observation.front_camera_valid"
FORCE_KEY = "observation.force"
STATE_KEY = "observation.state"
OBJECT_POSE_KEY = "observation.object_pose"
GOAL_KEY = "observation.goal"
ACTION_KEY = "action"
MIN_IMAGE_SIZE = 32  # SVT-AV1 (lerobot's default codec) dies of SIGFPE on 16x16 frames
FAULTS_STREAM = 1  # keeps the fault generator independent of the episode's pusher generator


class RecordError(ValueError):
    """Bad arguments or destination, or a recording worker that failed; the message names the
    problem (and the episodes the worker recorded)."""


@dataclass(frozen=True)
class SensorFaults:
    """Seeded sensor outages, written into an episode as data.

    Each kind of outage starts a Poisson number of spans per episode, at uniform positions:
    force dropouts (values become NaN), black frames, and camera freezes (the last delivered
    frame repeats). Frozen and black frames are marked invalid.
    """

    force_dropouts: float = 1.0  # mean spans per episode
    force_dropout_steps: tuple[int, int] = (3, 15)  # span length range, inclusive
    camera_freezes: float = 0.7
    camera_freeze_steps: tuple[int, int] = (3, 10)
    black_frames: float = 0.5
    black_frame_steps: tuple[int, int] = (1, 5)

    def apply(self, episode: dict[str, np.ndarray], rng: np.random.Generator) -> None:
        """Corrupt ``episode`` (from `rollout`) in place and set its ``image_valid``."""
        steps = len(episode["force"])
        for start, stop in self._spans(rng, steps, self.force_dropouts, self.force_dropout_steps):
            episode["force"][start:stop] = np.nan
        for start, stop in self._spans(rng, steps, self.black_frames, self.black_frame_steps):
            episode["image"][start:stop] = 0
            episode["image_valid"][start:stop] = False
        # After the black frames: a frozen camera repeats whatever it delivered last, black or not.
        for start, stop in self._spans(rng, steps, self.camera_freezes, self.camera_freeze_steps):
            # A camera that freezes at t=0 has no earlier frame to repeat: it shows black.
            episode["image"][start:stop] = episode["image"][start - 1] if start > 0 else 0
            episode["image_valid"][start:stop] = False

    @staticmethod
    def _spans(rng: np.random.Generator, steps: int, rate: float, lengths: tuple[int, int]):
        for _ in range(rng.poisson(rate)):
            start = int(rng.integers(steps))
            yield start, min(steps, start + int(rng.integers(lengths[0], lengths[1] + 1)))


def dataset_features(image_size: int) -> dict[str, dict]:
    def vector(names: list[str]) -> dict:
        return {"dtype": "float32", "shape": (len(names),), "names": list(names)}

    return {
        CAMERA_KEY: {
            "dtype": "video",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        },
        CAMERA_VALID_KEY: {"dtype": "bool", "shape": (1,), "names": ["valid"]},
        FORCE_KEY: vector(FORCE_NAMES),
        STATE_KEY: vector(PROPRIO_NAMES),
        OBJECT_POSE_KEY: vector(OBJECT_POSE_NAMES),
        GOAL_KEY: vector(GOAL_NAMES),
        ACTION_KEY: vector(ACTION_NAMES),
    }


@dataclass(frozen=True)
class RecordConfig:
    """What `record` records: ``mmf-rl record``'s options.

    Args:
        out: the dataset directory to create.
        episodes: how many episodes to record.
        workers: recording processes; episode ``i`` is the same whatever the number.
        seed: episode ``i`` depends only on ``(seed, i)``, so a recording can be repeated or extended.
        image_size: the camera image's side in pixels.
        steps: steps per episode, at the env's 25 Hz.
        camera: ``"front"``, ``"top"``, or a camera of the model XML.
        faults: write seeded sensor outages (force dropouts, black and frozen frames, with the
            camera's validity flag) into the data, for training on faults the data really has.
        exploration: the per-step probability of a random-move burst of the pusher, so a world
            model also sees moves that miss or bump the block.
        steady: the scripted pusher acts in one steady style (`PusherStyle.steady`: no noise,
            pauses or re-approach whims) instead of a style drawn per episode: demonstrations to
            imitate rather than data to forecast.
        overwrite: replace an existing ``out`` instead of refusing.
        repo_id: the LeRobot ``repo_id`` stored in the metadata.
        vcodec: the video codec lerobot encodes the camera with.
        policy: ``None``: the scripted pusher. Else a picklable factory of the `Actor` that records
            (called once per worker process): e.g. `mmf_rl.rl.PushMPCAgent`.
    """

    out: Path
    episodes: int
    workers: int = 1
    seed: int = 0
    image_size: int = 64
    steps: int = 50
    camera: str = "front"
    faults: bool = False
    exploration: float = 0.0
    steady: bool = False
    overwrite: bool = False
    repo_id: str = "local/mmf-push"
    vcodec: str = "libsvtav1"
    policy: Callable[[], Actor] | None = None


# The options that decide what each episode holds; ``workers`` and ``overwrite`` do not: episode i
# depends only on (seed, i).
EPISODE_OPTIONS = ("seed", "image_size", "steps", "camera", "faults", "exploration", "steady", "vcodec")
# What a recording's provenance keeps: those, how many episodes, and its name.
PROVENANCE_OPTIONS = ("episodes", *EPISODE_OPTIONS, "repo_id")


def recording_provenance(config: RecordConfig) -> dict:
    """What `record` writes to ``meta/mmf_rl_recording.json``: the options that define the data, the
    policy that acted (``None``: the scripted pusher; else its factory's name or description) and the
    mmf-rl version."""
    policy = config.policy
    name = None if policy is None else getattr(policy, "__qualname__", None) or str(policy)
    options = {option: getattr(config, option) for option in PROVENANCE_OPTIONS}
    return {**options, "policy": name, "mmf_rl_version": mmf_rl.__version__}


def _write_provenance(dataset_root: Path, provenance: dict) -> None:
    """Into the staged dataset: it is published with the dataset, by the same rename."""
    (dataset_root / PROVENANCE_FILE).write_text(json.dumps(provenance, indent=2) + "\n")


def record_episode(
    env, config: RecordConfig, episode_index: int, actor: Actor | None = None
) -> dict[str, np.ndarray]:
    """Roll out episode ``episode_index`` (with ``actor``, built from ``config.policy``, if any) and
    apply its sensor faults when enabled."""
    episode = rollout(env, config.seed, episode_index, config.steps, config.exploration, actor, config.steady)
    episode["image_valid"] = np.ones((config.steps, 1), dtype=bool)
    if config.faults:
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, episode_index, FAULTS_STREAM]))
        SensorFaults().apply(episode, rng)
    return episode


def record_shard(
    config: RecordConfig, root: Path, episode_indices: range, progress: Callable[[int], None]
) -> None:
    """Record ``episode_indices`` into a new LeRobot dataset at ``root``; ``progress(index)`` after
    each episode."""
    from datasets.utils.logging import disable_progress_bar
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    disable_progress_bar()  # lerobot's per-episode "Map" bars would drown the episodes bar

    env = MultimodalPushEnv(image_size=config.image_size, camera=config.camera)
    actor = config.policy() if config.policy is not None else None
    try:
        dataset = LeRobotDataset.create(
            repo_id=config.repo_id,
            fps=round(1.0 / env.dt),
            features=dataset_features(config.image_size),
            root=root,
            robot_type=ROBOT_TYPE,
            use_videos=True,
            vcodec=config.vcodec,
        )
        for index in episode_indices:
            episode = record_episode(env, config, index, actor)
            for t in range(config.steps):
                dataset.add_frame(
                    {
                        CAMERA_KEY: episode["image"][t],
                        CAMERA_VALID_KEY: episode["image_valid"][t],
                        FORCE_KEY: episode["force"][t],
                        STATE_KEY: episode["proprio"][t],
                        OBJECT_POSE_KEY: episode["object_pose"][t],
                        GOAL_KEY: episode["goal"][t],
                        ACTION_KEY: episode["action"][t],
                        "task": TASK,
                    }
                )
            # One encoder process per worker: the workers already fill the cores.
            dataset.save_episode(parallel_encoding=False)
            progress(index)
        dataset.finalize()
    finally:
        env.close()


def _check_destination(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise RecordError(f"--out {out} is a file; choose a directory path.")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise RecordError(
            f"--out {out} already exists and is not empty; pass --overwrite to replace it, "
            "or choose another directory."
        )
    parent = out.parent
    existing = next(p for p in (parent, *parent.parents) if p.exists())
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise RecordError(f"cannot write to {existing} (needed for --out {out}); choose a writable --out.")


def _validate(config: RecordConfig) -> None:
    for name, value, minimum in (
        ("--episodes", config.episodes, 1),
        ("--workers", config.workers, 1),
        ("--steps", config.steps, 1),
        ("--image-size", config.image_size, MIN_IMAGE_SIZE),
    ):
        if value < minimum:
            raise RecordError(f"{name} {value}: must be at least {minimum}.")
    if config.seed < 0:
        raise RecordError(f"--seed {config.seed}: must be non-negative.")
    if not 0.0 <= config.exploration <= 1.0:
        raise RecordError(f"--exploration {config.exploration}: must be a probability in [0, 1].")
    if config.steady and config.policy is not None:
        raise RecordError(
            "--steady sets the scripted pusher's style, but --policy acts instead of it; drop one."
        )
    _check_destination(config.out, config.overwrite)
    # Slower checks last: this one imports lerobot.
    if config.camera not in camera_names():
        raise RecordError(f"--camera {config.camera!r} is unknown; choose one of {camera_names()}.")
    from lerobot.datasets.video_utils import VALID_VIDEO_CODECS

    if config.vcodec not in VALID_VIDEO_CODECS:
        raise RecordError(
            f"--vcodec {config.vcodec!r} is unknown; choose one of {sorted(VALID_VIDEO_CODECS)}."
        )


def _shard_ranges(episodes: int, workers: int) -> list[range]:
    bounds = np.linspace(0, episodes, workers + 1).round().astype(int)
    return [range(a, b) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _record_shards(config: RecordConfig, shard_roots: list[Path], ranges: list[range], bar) -> None:
    """Record each range of episodes into its shard root, each in a worker process of its own."""
    shards = [(config, root, indices) for root, indices in zip(shard_roots, ranges, strict=True)]
    try:
        run_shards(record_shard, shards, lambda _shard, _episode: bar.update(1))
    except ShardError as failure:
        failed = ranges[failure.shard]
        raise RecordError(
            f"recording episodes {failed.start}-{failed.stop - 1} failed: {failure.detail}"
        ) from None


def partial_prefix(out: Path) -> str:
    """Name prefix of the temporary directories of recordings into ``out`` (beside it)."""
    return f".{out.name}.partial-"


def _staging(out: Path) -> contextlib.AbstractContextManager[Path]:
    """A temp dir beside ``out`` (the same file system: the result is renamed into place), removed
    on exit; those of recordings that were killed are removed first."""
    return staging_dir(out.parent, partial_prefix(out), "choose a writable --out.")


def _publish(dataset_root: Path, out: Path, work: Path) -> None:
    """Rename the finished dataset to ``out``, replacing what is there (overwrite was checked)."""
    if out.exists():
        replaced = work / "replaced"
        out.rename(replaced)
        try:
            dataset_root.rename(out)
        except OSError:
            replaced.rename(out)  # keep the old dataset rather than nothing
            raise
    else:
        dataset_root.rename(out)


def record(config: RecordConfig) -> Path:
    """Record ``config.episodes`` episodes into ``config.out``; return the dataset's path."""
    _validate(config)
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints its whole config per episode otherwise
    out = config.out.resolve()
    with _staging(out) as work:
        ranges = _shard_ranges(config.episodes, config.workers)
        shard_roots = [work / f"shard-{k}" for k in range(len(ranges))]
        with tqdm(total=config.episodes, unit="episode", desc="recording", dynamic_ncols=True) as bar:
            if len(ranges) == 1:  # no worker process: spares a second import of torch and lerobot
                record_shard(config, shard_roots[0], ranges[0], lambda _: bar.update(1))
            else:
                _record_shards(config, shard_roots, ranges, bar)
        dataset_root = work / "dataset"
        join_shards(shard_roots, dataset_root, config.repo_id)
        _write_provenance(dataset_root, recording_provenance(config))
        _publish(dataset_root, out, work)
    return out


def _differences(first: dict, other: dict) -> list[str]:
    """The feature names whose description differs between two datasets' ``features``."""
    return sorted(k for k in first.keys() | other.keys() if first.get(k) != other.get(k))


def merge_recordings(
    sources: Sequence[Path], out: Path, overwrite: bool = False, repo_id: str = RecordConfig.repo_id
) -> Path:
    """Concatenate LeRobot datasets into a new one at ``out``: the episodes of ``sources[0]``, then
    of ``sources[1]``, ..., renumbered from 0 (statistics merged). Return ``out``.

    lerobot's `aggregate_datasets` does the work (it also joins `record`'s shards); its own CLI
    (``lerobot-edit-dataset --operation.type merge``) loads every source from one ``--root``, so it
    cannot merge local recordings kept in separate directories. The sources must share fps, robot
    type and features (names, shapes, video codec): two recordings of `mmf-rl record` with the same
    ``--image-size``, ``--camera`` and ``--vcodec`` do. Like `record`, the result is built beside
    ``out`` and renamed into place: an interrupted merge leaves nothing at ``out``.
    """
    sources = [Path(source).resolve() for source in sources]
    out = Path(out).resolve()
    if len(sources) < 2:
        raise RecordError(f"--merge needs at least two datasets, found {len(sources)}.")
    for source in sources:
        if not (source / "meta" / "info.json").is_file():
            raise RecordError(
                f"--merge {source}: not a LeRobot dataset (no meta/info.json); give the directories "
                "of finished recordings."
            )
    if out in sources:
        raise RecordError(f"--out {out} is one of the --merge datasets; write the union to a new directory.")
    try:
        provenance = {"merged": [read_recording_provenance(source) for source in sources]}
    except ValueError as error:
        raise RecordError(f"--merge: {error}") from None
    _check_destination(out, overwrite)
    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    metadata = [LeRobotDatasetMetadata(repo_id, root=source) for source in sources]
    first = metadata[0]
    for source, meta in zip(sources[1:], metadata[1:], strict=True):
        # lerobot checks the same, but prints both whole feature dicts: name the differences.
        if meta.fps != first.fps or meta.robot_type != first.robot_type:
            raise RecordError(
                f"--merge {source}: fps {meta.fps}, robot {meta.robot_type!r}; {sources[0]} has fps "
                f"{first.fps}, robot {first.robot_type!r}. Only recordings of one setup merge."
            )
        differing = _differences(first.features, meta.features)
        if differing:
            raise RecordError(
                f"--merge {source}: features {differing} differ from those of {sources[0]} (e.g. another "
                "--image-size, --camera or --vcodec); only recordings with the same features merge."
            )
    with _staging(out) as work:
        dataset_root = work / "dataset"
        aggregate_datasets(
            repo_ids=[repo_id] * len(sources), aggr_repo_id=repo_id, roots=sources, aggr_root=dataset_root
        )
        _write_provenance(dataset_root, provenance)
        _publish(dataset_root, out, work)
    return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Record pushes (scripted, or by an agent) as a LeRobot v3.0 dataset, or merge recordings."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
        "  mmf-rl record --out data/push --episodes 200 --workers 2 --image-size 64 --steps 50\n"
        "  mmf-rl record --out data/push_faults --episodes 100 --faults   # with sensor outages in the data\n"
        "  mmf-rl record --out data/push_mpc --episodes 100 --exploration 0.1 --policy runs/world_model  # "
        "by MPC\n"
        "  mmf-rl record --merge data/push data/push_more --out data/push_all   # one dataset of both",
    )
    parser.add_argument("--out", type=Path, required=True, help="dataset directory to create")
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--episodes", type=int, help="number of episodes")
    what.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        metavar="DATASET",
        help="instead of recording, write the episodes of these recordings (same features) to --out",
    )
    parser.add_argument("--workers", type=int, default=1, help="recording processes (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="episode i depends only on (seed, i)")
    parser.add_argument("--image-size", type=int, default=64, help="camera image side in pixels")
    parser.add_argument("--steps", type=int, default=50, help="steps per episode, at 25 Hz")
    parser.add_argument("--camera", default="front", help="'front', 'top', or a camera of the model XML")
    parser.add_argument("--faults", action="store_true", help="write seeded sensor outages into the data")
    parser.add_argument(
        "--exploration",
        type=float,
        default=0.0,
        help="per-step probability of a random-move burst (data for world models; default 0)",
    )
    parser.add_argument(
        "--steady",
        action="store_true",
        help="the pusher in one steady style, without noise, pauses or whims (demonstrations for imitation)",
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument(
        "--repo-id", default=RecordConfig.repo_id, help="LeRobot repo_id stored in the metadata"
    )
    parser.add_argument(
        "--vcodec",
        default=RecordConfig.vcodec,
        help="video codec for the camera (lerobot's choices: libsvtav1, h264, hevc, ...)",
    )
    return parser


# Options of a recording that a merge has no use for (their defaults are RecordConfig's).
RECORDING_OPTIONS = ("workers", *EPISODE_OPTIONS)


def run(args: argparse.Namespace, policy: Callable[[], Actor] | None = None) -> int:
    """Record (with ``policy``, see `RecordConfig.policy`) or merge, as ``args`` (`build_parser`) say."""
    try:
        if args.merge:
            given = [
                f"--{n.replace('_', '-')}"
                for n in RECORDING_OPTIONS
                if getattr(args, n) != getattr(RecordConfig, n)
            ]
            given += ["--policy"] if policy is not None else []
            if given:
                raise RecordError(f"--merge records nothing: {', '.join(given)} would be ignored; drop them.")
            out = merge_recordings(args.merge, args.out, args.overwrite, args.repo_id)
            print(f"merged {len(args.merge)} recordings into {out}")
            return 0
        config = RecordConfig(
            out=args.out,
            episodes=args.episodes,
            workers=args.workers,
            seed=args.seed,
            image_size=args.image_size,
            steps=args.steps,
            camera=args.camera,
            faults=args.faults,
            exploration=args.exploration,
            steady=args.steady,
            overwrite=args.overwrite,
            repo_id=args.repo_id,
            vcodec=args.vcodec,
            policy=policy,
        )
        out = record(config)
    except (RecordError, StagingError) as error:
        print(f"{PROG}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written to {args.out}", file=sys.stderr)
        return 130
    print(f"recorded {config.episodes} episodes to {out}" + (f" with {policy}" if policy is not None else ""))
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
