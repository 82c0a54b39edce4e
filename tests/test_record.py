"""`mmf-rl record`: recorded datasets load back with lerobot, match the rollouts, fail cleanly."""

from __future__ import annotations

import json
import os
import re
import shutil

os.environ.setdefault("HF_HUB_OFFLINE", "1")  # before lerobot / huggingface_hub load

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch

import mmf_rl
from mmf_rl import cli
from mmf_rl import record as record_module
from mmf_rl.datasets.provenance import PROVENANCE_FILE, read_recording_provenance
from mmf_rl.record import (
    ACTION_KEY,
    CAMERA_KEY,
    CAMERA_VALID_KEY,
    FORCE_KEY,
    GOAL_KEY,
    OBJECT_POSE_KEY,
    STATE_KEY,
    TASK,
    RecordConfig,
    RecordError,
    SensorFaults,
    merge_recordings,
    record,
    record_episode,
)

EPISODES = 2
STEPS = 40
IMAGE_SIZE = 64
VECTOR_KEYS = {FORCE_KEY: 6, STATE_KEY: 17, OBJECT_POSE_KEY: 7, GOAL_KEY: 3, ACTION_KEY: 4}


def load(root: Path):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(RecordConfig.repo_id, root=root)


def columns(dataset, episode: int) -> dict[str, np.ndarray]:
    """The parquet (non-video) columns of one episode, as float32 / bool arrays."""
    table = dataset.hf_dataset.with_format("numpy")
    keep = np.flatnonzero(np.asarray(table["episode_index"]) == episode)
    rows = table.select(keep)
    out = {key: np.stack(rows[key]) for key in VECTOR_KEYS}
    out[CAMERA_VALID_KEY] = np.stack(rows[CAMERA_VALID_KEY]).reshape(-1, 1)
    return out


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> RecordConfig:
    return RecordConfig(
        out=tmp_path_factory.mktemp("record") / "push",
        episodes=EPISODES,
        workers=1,
        seed=0,
        image_size=IMAGE_SIZE,
        steps=STEPS,
    )


@pytest.fixture(scope="module")
def recorded(config) -> Path:
    return record(config)


@pytest.fixture(scope="module")
def push_env():
    from mmf_rl.envs.push import MultimodalPushEnv

    env = MultimodalPushEnv(image_size=IMAGE_SIZE)
    yield env
    env.close()


def test_dataset_loads_back_with_lerobot(recorded):
    dataset = load(recorded)
    assert dataset.num_episodes == EPISODES and dataset.num_frames == EPISODES * STEPS
    assert dataset.fps == 25
    assert dataset.meta.info["codebase_version"] == "v3.0"
    assert dataset.meta.video_keys == [CAMERA_KEY]
    for key, width in VECTOR_KEYS.items():
        feature = dataset.features[key]
        assert feature["dtype"] == "float32" and tuple(feature["shape"]) == (width,), key
        assert len(feature["names"]) == width, key
    assert dataset.features[CAMERA_VALID_KEY]["dtype"] == "bool"

    first, last = dataset[0], dataset[STEPS - 1]
    assert first[CAMERA_KEY].shape == (3, IMAGE_SIZE, IMAGE_SIZE)
    assert first[FORCE_KEY].shape == (6,) and first[STATE_KEY].shape == (17,)
    assert first["task"] == TASK
    assert first[CAMERA_KEY].std() > 0.05, "the camera sees a scene"
    assert (first[CAMERA_KEY] - last[CAMERA_KEY]).abs().mean() > 0.005, "and the scene changes"


def test_dataset_holds_the_seeded_rollouts(recorded, config, push_env):
    """Episode i is exactly `record_episode(seed, i)`: numbers bit-for-bit, video up to the codec."""
    dataset = load(recorded)
    for episode in range(EPISODES):
        expected = record_episode(push_env, config, episode)
        stored = columns(dataset, episode)
        for key, name in (
            (FORCE_KEY, "force"),
            (STATE_KEY, "proprio"),
            (OBJECT_POSE_KEY, "object_pose"),
            (GOAL_KEY, "goal"),
            (ACTION_KEY, "action"),
            (CAMERA_VALID_KEY, "image_valid"),
        ):
            np.testing.assert_array_equal(stored[key], expected[name], err_msg=key)
        start = int(dataset.meta.episodes["dataset_from_index"][episode])
        for t in (0, STEPS // 2, STEPS - 1):
            decoded = dataset[start + t][CAMERA_KEY].permute(1, 2, 0).numpy() * 255
            assert np.abs(decoded - expected["image"][t]).mean() < 8, "video frame matches the render"


def test_pushes_show_contact_forces(recorded):
    dataset = load(recorded)
    for episode in range(EPISODES):
        force = columns(dataset, episode)[FORCE_KEY]
        assert np.all(np.isfinite(force))
        assert np.count_nonzero(np.linalg.norm(force[:, :3], axis=1) > 1.0) >= 2, episode


@pytest.fixture(scope="module")
def two_workers_recorded(config) -> Path:
    """``config`` recorded again by 2 worker processes (spawned, each importing torch and lerobot)."""
    return record(replace(config, out=config.out.parent / "two_workers", workers=2))


def test_worker_count_does_not_change_the_episodes(recorded, two_workers_recorded):
    one, two = load(recorded), load(two_workers_recorded)
    assert two.num_episodes == EPISODES and two.num_frames == EPISODES * STEPS
    for episode in range(EPISODES):
        a, b = columns(one, episode), columns(two, episode)
        for key in a:
            np.testing.assert_array_equal(a[key], b[key], err_msg=f"episode {episode} {key}")
    # Nor what the recording says of itself.
    assert read_recording_provenance(two_workers_recorded) == read_recording_provenance(recorded)


def test_a_recording_says_how_it_was_made(recorded, capsys):
    assert read_recording_provenance(recorded) == {
        "episodes": EPISODES,
        "seed": 0,
        "image_size": IMAGE_SIZE,
        "steps": STEPS,
        "camera": "front",
        "faults": False,
        "exploration": 0.0,
        "steady": False,
        "vcodec": RecordConfig.vcodec,
        "repo_id": RecordConfig.repo_id,
        "policy": None,
        "mmf_rl_version": mmf_rl.__version__,
    }
    assert cli.main(["inspect", str(recorded)]) == 0
    shown = [line for line in capsys.readouterr().out.splitlines() if "mmf-rl record" in line]
    assert shown == [
        f"  recorded by mmf-rl record: {EPISODES} episodes of {STEPS} steps, seed 0, scripted pusher, a "
        f"style drawn per episode, exploration 0.0, no faults, front camera {IMAGE_SIZE} px (libsvtav1), "
        f"mmf-rl {mmf_rl.__version__}"
    ]


@pytest.mark.slow
def test_a_steady_recording_says_so_and_not_its_worker_count(config, two_workers_recorded, tmp_path):
    # In this process; the worker count is left out of the 2-worker recording's provenance (above).
    steady = replace(config, out=tmp_path / "steady", steady=True, steps=3, seed=7)
    provenance = read_recording_provenance(record(steady))
    assert provenance["steady"] is True and provenance["seed"] == 7 and provenance["steps"] == 3
    assert "workers" not in provenance and "overwrite" not in provenance
    assert json.loads((steady.out / PROVENANCE_FILE).read_text()) == provenance
    two_workers = read_recording_provenance(two_workers_recorded)
    assert "workers" not in two_workers and "overwrite" not in two_workers


@pytest.mark.slow
def test_faults_are_written_as_data(config, push_env, tmp_path):
    # Seed 5 draws force dropouts and camera outages in both of its first two episodes.
    faulty = replace(config, out=tmp_path / "faulty", seed=5, faults=True)
    dataset = load(record(faulty))
    for episode in range(EPISODES):
        stored = columns(dataset, episode)
        expected = record_episode(push_env, faulty, episode)
        clean = record_episode(push_env, replace(faulty, faults=False), episode)
        dropped = np.isnan(stored[FORCE_KEY]).any(axis=1)
        invalid = ~stored[CAMERA_VALID_KEY][:, 0]
        assert dropped.any() and invalid.any(), episode
        assert np.isnan(stored[FORCE_KEY][dropped]).all(), "a dropout loses the whole wrench"
        np.testing.assert_array_equal(stored[FORCE_KEY], expected["force"])  # NaN where expected
        np.testing.assert_array_equal(stored[FORCE_KEY][~dropped], clean["force"][~dropped])
        np.testing.assert_array_equal(stored[CAMERA_VALID_KEY], expected["image_valid"])
        np.testing.assert_array_equal(stored[OBJECT_POSE_KEY], clean["object_pose"])

        # The video carries the corrupted frames (up to the codec); clean frames stay as rendered.
        assert not np.array_equal(expected["image"][invalid], clean["image"][invalid])
        np.testing.assert_array_equal(expected["image"][~invalid], clean["image"][~invalid])
        start = int(dataset.meta.episodes["dataset_from_index"][episode])
        for t in np.flatnonzero(invalid):
            decoded = dataset[start + t][CAMERA_KEY].permute(1, 2, 0).numpy() * 255
            assert np.abs(decoded - expected["image"][t]).mean() < 8, (episode, t)


def test_sensor_faults_are_seeded_spans():
    steps = 60
    episode = {
        "force": np.ones((steps, 6), np.float32),
        "image": np.arange(steps, dtype=np.uint8)[:, None, None, None].repeat(4, 1).repeat(4, 2).repeat(3, 3)
        + 1,
        "image_valid": np.ones((steps, 1), bool),
    }
    faults = SensorFaults(force_dropouts=3, camera_freezes=2, black_frames=2)
    first = {k: v.copy() for k, v in episode.items()}
    faults.apply(first, np.random.default_rng(0))
    again = {k: v.copy() for k, v in episode.items()}
    faults.apply(again, np.random.default_rng(0))
    for key in first:
        np.testing.assert_array_equal(first[key], again[key])

    assert np.isnan(first["force"]).any() and not np.isnan(first["force"]).all()
    invalid = ~first["image_valid"][:, 0]
    assert invalid.any()
    for t in range(steps):
        if not invalid[t]:
            np.testing.assert_array_equal(first["image"][t], episode["image"][t])
        else:
            black = (first["image"][t] == 0).all()
            frozen = t > 0 and (first["image"][t] == first["image"][t - 1]).all()
            assert black or frozen, t


def _run_cli(argv, capsys) -> tuple[int, str]:
    code = cli.main(["record", *argv])
    return code, capsys.readouterr().err.strip()


def _assert_one_line_error(code: int, err: str, *words: str):
    assert code == 2
    last = err.splitlines()[-1]
    assert last.startswith("mmf-rl record: error: "), err
    assert "Traceback" not in err
    for word in words:
        assert word in last, (word, last)


def test_zero_episodes_is_a_clear_error(tmp_path, capsys):
    code, err = _run_cli(["--out", str(tmp_path / "x"), "--episodes", "0"], capsys)
    _assert_one_line_error(code, err, "--episodes 0", "at least 1")
    assert not (tmp_path / "x").exists()


def test_exploration_outside_zero_one_is_a_clear_error(tmp_path, capsys):
    code, err = _run_cli(["--out", str(tmp_path / "x"), "--episodes", "1", "--exploration", "2"], capsys)
    _assert_one_line_error(code, err, "--exploration 2.0", "probability in [0, 1]")
    assert not (tmp_path / "x").exists()


def test_steady_with_a_policy_is_a_clear_error(tmp_path):
    config = RecordConfig(out=tmp_path / "x", episodes=1, steady=True, policy=DrawnDirectionPolicy())
    with pytest.raises(RecordError, match="--steady sets the scripted pusher's style, but --policy acts"):
        record(config)
    assert not (tmp_path / "x").exists()


def test_unwritable_out_is_a_clear_error(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    code, err = _run_cli(["--out", str(blocker / "push"), "--episodes", "1"], capsys)
    _assert_one_line_error(code, err, str(blocker), "writable --out")


def test_existing_out_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "push"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    code, err = _run_cli(["--out", str(out), "--episodes", "1"], capsys)
    _assert_one_line_error(code, err, str(out), "--overwrite")
    assert (out / "keep.txt").read_text() == "precious"

    code, _ = _run_cli(["--out", str(out), "--episodes", "1", "--steps", "3", "--overwrite"], capsys)
    assert code == 0
    assert not (out / "keep.txt").exists() and load(out).num_frames == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == ["push"], "no temporary directory left behind"


def test_interrupted_recording_leaves_nothing(tmp_path, capsys, monkeypatch):
    real_record_shard = record_module.record_shard

    def interrupted(config, root, episode_indices, on_episode):
        real_record_shard(config, root, range(1), on_episode)  # a shard with one finished episode...
        raise KeyboardInterrupt  # ...then Ctrl-C

    monkeypatch.setattr(record_module, "record_shard", interrupted)
    out = tmp_path / "push"
    code, err = _run_cli(["--out", str(out), "--episodes", "2", "--steps", "3"], capsys)
    assert code == 130 and "interrupted" in err
    assert list(tmp_path.iterdir()) == [], "neither --out nor a temporary directory remains"


@dataclass(frozen=True)
class UnloadablePolicy:
    """A `RecordConfig.policy` factory that fails in each worker process that calls it."""

    def __call__(self):
        raise ValueError("no world model in runs/missing")


@pytest.mark.slow
def test_a_failing_worker_is_a_one_line_error_naming_its_episodes(tmp_path, capsys):
    args = record_module.build_parser().parse_args(
        ["--out", str(tmp_path / "push"), "--episodes", "4", "--workers", "2", "--steps", "3"]
    )
    code = record_module.run(args, UnloadablePolicy())
    err = capsys.readouterr().err.strip()
    _assert_one_line_error(code, err, "failed: ValueError: no world model in runs/missing")
    assert re.search(r"recording episodes (0-1|2-3) failed", err), err
    assert list(tmp_path.iterdir()) == [], "neither --out nor a temporary directory remains"


# --- recording with an injected policy, merging recordings ----------------------------------------


class DrawnDirection:
    """An `Actor`: each episode pushes one direction drawn from the episode's generator."""

    def reset(self, rng):
        self.action = np.r_[rng.uniform(-1.0, 1.0, 3), 0.0].astype(np.float32)

    def act(self, obs):
        return self.action


@dataclass(frozen=True)
class DrawnDirectionPolicy:
    """The picklable factory `RecordConfig.policy` takes."""

    def __call__(self) -> DrawnDirection:
        return DrawnDirection()


@pytest.fixture(scope="module")
def policy_recorded(config) -> Path:
    return record(replace(config, out=config.out.parent / "policy", seed=1, policy=DrawnDirectionPolicy()))


def test_an_injected_policy_records_its_episodes_with_the_same_features(
    policy_recorded, recorded, config, push_env
):
    dataset = load(policy_recorded)
    assert dataset.num_episodes == EPISODES and dataset.num_frames == EPISODES * STEPS
    assert dataset.meta.features == load(recorded).meta.features, "the recordings merge and train alike"
    assert read_recording_provenance(policy_recorded)["policy"] == "DrawnDirectionPolicy()"
    policy_config = replace(config, seed=1)
    for episode in range(EPISODES):
        expected = record_episode(push_env, policy_config, episode, DrawnDirection())
        stored = columns(dataset, episode)
        np.testing.assert_array_equal(stored[ACTION_KEY], expected["action"])
        assert (stored[ACTION_KEY] == stored[ACTION_KEY][0]).all(), "the policy acted, not the pusher"
        np.testing.assert_array_equal(stored[OBJECT_POSE_KEY], expected["object_pose"])


def test_merge_holds_the_episodes_of_both_recordings_in_order(recorded, policy_recorded, tmp_path):
    merged = load(merge_recordings([recorded, policy_recorded], tmp_path / "union"))
    assert merged.num_episodes == 2 * EPISODES and merged.num_frames == 2 * EPISODES * STEPS
    assert merged.meta.info["codebase_version"] == "v3.0"
    for offset, source in ((0, load(recorded)), (EPISODES, load(policy_recorded))):
        for episode in range(EPISODES):
            a, b = columns(source, episode), columns(merged, offset + episode)
            for key in a:
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{offset + episode} {key}")
    start = int(merged.meta.episodes["dataset_from_index"][EPISODES])
    assert merged[start][CAMERA_KEY].shape == (3, IMAGE_SIZE, IMAGE_SIZE), "the videos were merged too"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["union"], "no temporary directory left behind"
    sources = [read_recording_provenance(root) for root in (recorded, policy_recorded)]
    assert read_recording_provenance(tmp_path / "union") == {"merged": sources}


def test_merge_of_a_recording_without_provenance_lists_it_as_null(recorded, tmp_path):
    older = Path(shutil.copytree(recorded, tmp_path / "older"))  # as recorded before the file existed
    (older / PROVENANCE_FILE).unlink()
    assert read_recording_provenance(older) is None
    merged = merge_recordings([older, recorded], tmp_path / "union")
    assert read_recording_provenance(merged) == {"merged": [None, read_recording_provenance(recorded)]}
    assert load(merged).num_episodes == 2 * EPISODES

    (older / PROVENANCE_FILE).write_text("{damaged")
    with pytest.raises(RecordError, match=re.escape(f"{older / PROVENANCE_FILE}: not valid JSON")):
        merge_recordings([older, recorded], tmp_path / "again")
    assert not (tmp_path / "again").exists()


def test_merge_of_recordings_with_other_features_is_a_clear_error(recorded, recorded_push_root, tmp_path):
    with pytest.raises(RecordError, match=r"features \['observation\.images\.front'\] differ.*--image-size"):
        merge_recordings([recorded, recorded_push_root], tmp_path / "union")  # 64 px and 32 px
    assert not (tmp_path / "union").exists()


def test_merge_errors_name_the_path_and_the_fix(recorded, tmp_path, capsys):
    not_a_dataset = tmp_path / "empty"
    not_a_dataset.mkdir()
    code, err = _run_cli(["--merge", str(recorded), str(not_a_dataset), "--out", str(tmp_path / "u")], capsys)
    _assert_one_line_error(code, err, str(not_a_dataset), "not a LeRobot dataset")
    code, err = _run_cli(["--merge", str(recorded), str(recorded), "--out", str(recorded)], capsys)
    _assert_one_line_error(code, err, str(recorded), "new directory")
    code, err = _run_cli(
        ["--merge", str(recorded), str(recorded), "--out", str(tmp_path / "u"), "--seed", "3"], capsys
    )
    _assert_one_line_error(code, err, "--seed", "would be ignored")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


# --- `mmf-rl record --policy CHECKPOINT`: MPC on a (tiny) trained world model ---------------------

MPC_STEPS = 12  # > history 4 + horizon 3 of the tiny world model: every episode has windows
MPC_OPTIONS = ["--candidates", "16", "--iterations", "1", "--elites", "4", "--image-size", "32"]


def test_policy_checkpoint_records_mpc_episodes_that_merge_and_load_in_the_pipeline(
    push_world_model_run, recorded_push_root, tmp_path, capsys
):
    from mmf_rl.configuration import compose_config, to_container
    from mmf_rl.datasets import DataConfig, WindowDataset
    from mmf_rl.keys import validate_batch

    out = tmp_path / "mpc"
    argv = ["--out", str(out), "--episodes", "2", "--steps", str(MPC_STEPS), "--workers", "2", "--seed", "4"]
    code, err = _run_cli(
        [*argv, "--exploration", "0.2", "--policy", str(push_world_model_run), *MPC_OPTIONS], capsys
    )
    assert code == 0, err
    dataset = load(out)
    assert dataset.num_episodes == 2 and dataset.num_frames == 2 * MPC_STEPS
    assert dataset.meta.features == load(recorded_push_root).meta.features
    for episode in range(2):
        actions = columns(dataset, episode)[ACTION_KEY]
        assert np.all(np.abs(actions) <= 1.0) and np.all(np.isfinite(actions))

    union = merge_recordings([recorded_push_root, out], tmp_path / "union")
    cfg = compose_config(
        "train",
        [
            "data=push_world_model",
            f"data.root={union}",
            f"data.cache_dir={tmp_path / 'cache'}",
            "data.image_size=[32,32]",
            "data.history=4",
            "data.horizon=3",
        ],
    )
    windows = WindowDataset(DataConfig.from_dict(to_container(cfg.data)), num_workers=0)
    original = load(recorded_push_root)
    assert len(windows) == original.num_frames - 6 * original.num_episodes + 2 * (MPC_STEPS - 6)
    batch = windows.batch(torch.arange(len(windows) - 2, len(windows)))  # windows of the MPC episodes
    validate_batch(batch, windows.specs, history=4, horizon=3, target_dim=2, require_target=True)


def test_bad_policy_path_is_a_clear_error_naming_it(tmp_path, capsys):
    missing = tmp_path / "runs" / "no_such_world_model"
    out = tmp_path / "mpc"
    code, err = _run_cli(["--out", str(out), "--episodes", "1", "--policy", str(missing)], capsys)
    _assert_one_line_error(code, err, f"--policy {missing}", "does not exist")
    assert not out.exists()
