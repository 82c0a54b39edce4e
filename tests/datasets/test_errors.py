"""Clear errors for datasets the pipeline cannot read, and the window cache's hygiene."""

import importlib.util
import json
import os
import re
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import torch

import mmf_rl.datasets.cache as cache
from benchmarks.synthetic.dataset import IMAGE_FEATURE, POSE_FEATURE, STATE_FEATURE
from mmf_rl import temp_dirs
from mmf_rl.datasets.lerobot_source import V21_CONVERTER
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import EPISODE_LENGTHS, synthetic_config

PACKAGE_DIR = Path(cache.__file__).parent


def open_quietly(config) -> WindowDataset:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WindowDataset(config)


def raises_clearly(error_type, match, config) -> str:
    """Open ``config`` expecting one clear error: raised by mmf-rl, no chained lerobot/pyarrow trace."""
    with pytest.raises(error_type, match=match) as excinfo:
        open_quietly(config)
    error = excinfo.value
    assert Path(excinfo.traceback[-1].path).parent == PACKAGE_DIR, "raised from deep inside a library"
    assert error.__cause__ is None and (error.__context__ is None or error.__suppress_context__)
    return str(error)


def edit_info(root: Path, edit) -> None:
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    edit(info)
    path.write_text(json.dumps(info))


# --- clear errors --------------------------------------------------------------------------------


def test_missing_root_and_a_directory_that_is_not_a_dataset(synthetic_root, tmp_path):
    absent = tmp_path / "no_such_dataset"
    raises_clearly(
        FileNotFoundError,
        rf"dataset root {absent} does not exist: set `root`",
        synthetic_config(absent, tmp_path / "cache"),
    )
    assert not absent.exists(), "nothing may be created at a missing root"

    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "notes.txt").write_text("not a dataset")
    raises_clearly(
        FileNotFoundError,
        r"not a LeRobot dataset: .*meta/info\.json does not exist \(found \['notes\.txt'\]\)",
        synthetic_config(plain, tmp_path / "cache"),
    )
    assert sorted(p.name for p in plain.iterdir()) == ["notes.txt"], "lerobot wrote into a non-dataset root"

    # One level too high: the dataset is a subdirectory.
    raises_clearly(
        FileNotFoundError,
        rf"did you mean `root: {synthetic_root}`\?",
        synthetic_config(synthetic_root.parent, tmp_path / "cache"),
    )


def test_non_numeric_target_names_the_feature_and_its_dtype(synthetic_copy, tmp_path):
    message = raises_clearly(
        ValueError,
        rf"target: feature '{re.escape(IMAGE_FEATURE)}' has dtype 'video' and shape \[32, 32, 3\]",
        synthetic_config(synthetic_copy, tmp_path, target=IMAGE_FEATURE),
    )
    assert "numeric vector" in message and f"'{POSE_FEATURE}'" in message and "'index'" not in message

    edit_info(
        synthetic_copy,
        lambda info: info["features"].update(
            {"language_instruction": {"dtype": "string", "shape": [1], "names": None}}
        ),
    )
    raises_clearly(
        ValueError,
        r"target: feature 'language_instruction' has dtype 'string'",
        synthetic_config(synthetic_copy, tmp_path, target="language_instruction"),
    )


@pytest.mark.parametrize("stride", [1, 2])
def test_window_longer_than_every_episode(synthetic_root, tmp_path, stride):
    longest = max(EPISODE_LENGTHS)
    horizon = 5
    history = (
        (longest - 1) // stride - horizon + 1
    )  # the longest window that fits: (H + T - 1) * s + 1 frames
    needed = (history + horizon) * stride + 1
    raises_clearly(
        ValueError,
        rf"history={history + 1} and horizon={horizon} at stride={stride} spans .* = {needed} frames, but "
        rf"the longest episode \(episode 0\) has {longest} frames\. Lower `history`, `horizon` or `stride`",
        synthetic_config(synthetic_root, tmp_path, history=history + 1, horizon=horizon, stride=stride),
    )
    fits = open_quietly(
        synthetic_config(synthetic_root, tmp_path, history=history, horizon=horizon, stride=stride)
    )
    assert len(fits) == (longest - 1) % stride + 1  # every start that still leaves a whole window


@pytest.mark.parametrize("layout", ["codebase_version", "episodes_jsonl"])
def test_v2_dataset_names_lerobots_converter(tmp_path, layout):
    root = tmp_path / "old_dataset"
    (root / "meta").mkdir(parents=True)
    if layout == "codebase_version":
        version = "v2.1"
    else:  # a v2 layout whose info.json claims v3.0
        version = "v3.0"
        (root / "meta" / "episodes.jsonl").write_text('{"episode_index": 0, "length": 10}\n')
    (root / "meta" / "info.json").write_text(json.dumps({"codebase_version": version, "features": {}}))
    command = f"python -m {V21_CONVERTER} --repo-id=old_dataset --root={tmp_path} --push-to-hub=false"
    message = raises_clearly(
        ValueError, r"is a LeRobot v2\.x dataset", synthetic_config(root, tmp_path / "cache")
    )
    assert f"codebase_version '{version}'" in message and command in message
    assert importlib.util.find_spec(V21_CONVERTER) is not None, (
        "the converter named in the message does not exist"
    )


def test_info_json_missing_keys_and_shapes_disagreeing_with_the_data(synthetic_copy, tmp_path):
    info_path = synthetic_copy / "meta" / "info.json"
    original = info_path.read_text()
    data_file = next((synthetic_copy / "data").rglob("*.parquet"))
    config = synthetic_config(synthetic_copy, tmp_path)

    edit_info(synthetic_copy, lambda info: info.pop("features"))
    raises_clearly(ValueError, rf"{info_path}: missing key\(s\) \['features'\]", config)

    info_path.write_text(original)
    edit_info(synthetic_copy, lambda info: info["features"][STATE_FEATURE].update(shape=[5]))
    raises_clearly(
        ValueError,
        rf"{data_file}: column '{STATE_FEATURE}' holds fixed_size_list<element: float>\[4\] \(4 value\(s\) "
        rf"per frame\), but {info_path} declares dtype 'float32' shape \[5\]; fix",
        config,
    )

    info_path.write_text(original)
    extra = {"dtype": "float32", "shape": [2], "names": None}
    edit_info(synthetic_copy, lambda info: info["features"].update({"observation.extra": extra}))
    raises_clearly(
        ValueError,
        rf"{data_file}: no column 'observation.extra', which {info_path} declares \(dtype 'float32' "
        r"shape \[2\]\); found columns \[",
        config,
    )

    info_path.write_text(original)
    edit_info(synthetic_copy, lambda info: info["features"][STATE_FEATURE].update(shape="4"))
    raises_clearly(ValueError, rf"{info_path}: feature '{STATE_FEATURE}' `shape` should be a list", config)

    info_path.write_text(original)
    assert open_quietly(config).built  # the restored dataset reads


@pytest.mark.parametrize("damaged", ["data", "meta/episodes"])
def test_truncated_parquet_names_the_file(synthetic_copy, tmp_path, damaged):
    path = next((synthetic_copy / damaged).rglob("*.parquet"))
    content = path.read_bytes()
    path.write_bytes(content[: len(content) // 2])
    raises_clearly(
        ValueError,
        rf"{path}: not a readable parquet file \({len(content) // 2} bytes; .*truncated",
        synthetic_config(synthetic_copy, tmp_path / "cache"),
    )
    assert not (tmp_path / "cache").exists()


def test_corrupted_parquet_page_names_the_file(synthetic_copy, tmp_path):
    # The footer is intact, so this surfaces only while reading the data, during the build.
    path = next((synthetic_copy / "data").rglob("*.parquet"))
    content = bytearray(path.read_bytes())
    content[200:2000] = bytes(b ^ 0x5A for b in content[200:2000])
    path.write_bytes(bytes(content))
    raises_clearly(
        ValueError,
        rf"{path}: not a readable parquet file",
        synthetic_config(synthetic_copy, tmp_path / "cache"),
    )
    assert list((tmp_path / "cache").iterdir()) == [], "the failed build left files behind"


# --- cache hygiene -------------------------------------------------------------------------------


def exited_pid() -> int:
    process = subprocess.Popen(["true"])
    process.wait()
    return process.pid


def make_temp_dir(cache_dir: Path, name: str, age_s: float = 0.0) -> Path:
    directory = cache_dir / name
    (directory / "frames").mkdir(parents=True)
    (directory / "frames" / "target.memmap").write_bytes(b"\0" * 64)
    stamp = time.time() - age_s
    for path in (directory / "frames" / "target.memmap", directory / "frames", directory):
        os.utime(path, (stamp, stamp))
    return directory


@pytest.mark.slow
def test_stale_build_dirs_are_removed_live_ones_kept(synthetic_root, tmp_path, monkeypatch):
    config = synthetic_config(synthetic_root, tmp_path)
    seen = []

    def killed_write(source, directory, num_workers):
        seen.append(directory.name)
        raise KeyboardInterrupt("simulated kill")

    monkeypatch.setattr(cache, "_write", killed_write)
    with pytest.raises(KeyboardInterrupt):
        open_quietly(config)
    monkeypatch.undo()
    # The build's temp dir carries its owner, so a later process can tell a dead build from a live one.
    own_prefix = f".building-{os.getpid()}-"
    assert seen[0].startswith(own_prefix)
    dead = make_temp_dir(tmp_path, seen[0].replace(own_prefix, f".building-{exited_pid()}-", 1))
    live = make_temp_dir(tmp_path, seen[0] + "x")  # this process: a build in progress
    reused_pid = make_temp_dir(tmp_path, seen[0] + "y", age_s=2 * temp_dirs.STALE_REUSED_PID_AGE_S)
    other_host_recent = make_temp_dir(tmp_path, ".building-123-otherhost-push-abc")
    other_host_old = make_temp_dir(
        tmp_path, ".building-123-otherhost-push-def", age_s=2 * temp_dirs.STALE_AGE_S
    )
    unnamed_old = make_temp_dir(tmp_path, ".building-push-0123abcd-ghi", age_s=2 * temp_dirs.STALE_AGE_S)

    dataset = open_quietly(config)
    assert dataset.built
    left = {p.name for p in tmp_path.iterdir()}
    assert left == {dataset.cache_path.name, live.name, other_host_recent.name}
    assert not {dead.name, reused_pid.name, other_host_old.name, unnamed_old.name} & left


def all_windows(dataset):
    return dataset.batch(torch.arange(len(dataset)))


def test_cache_changed_on_disk_is_detected_and_rebuilt(synthetic_root, tmp_path, monkeypatch):
    # Hash large files by samples here too (the images are 160 kB), to cover that path.
    monkeypatch.setattr(cache, "FULL_CHECKSUM_MAX_BYTES", 16 * 1024)
    monkeypatch.setattr(cache, "CHECKSUM_BLOCK", 1024)
    config = synthetic_config(synthetic_root, tmp_path)
    first = open_quietly(config)
    expected = all_windows(first)
    path = first.cache_path
    assert not open_quietly(config).built, "an untouched cache must be reused"

    def reopen_expecting(match):
        with pytest.warns(UserWarning, match=rf"window cache {path} is damaged: {match}; rebuilding it"):
            dataset = WindowDataset(config)
        assert dataset.built and dataset.cache_path == path
        torch.testing.assert_close(all_windows(dataset), expected)
        assert [p.name for p in tmp_path.iterdir()] == [path.name], "the damaged copy was left behind"

    image = path / "frames" / "obs" / "image.memmap"
    with open(image, "r+b") as f:  # one byte of the first frame, same size
        f.seek(100)
        byte = f.read(1)
        f.seek(100)
        f.write(bytes([byte[0] ^ 0xFF]))
    reopen_expecting(rf"{image} has changed since the build \(sha256 differs\)")

    target = path / "frames" / "target.memmap"
    size = target.stat().st_size
    os.truncate(target, size - 8)
    reopen_expecting(rf"{target} has {size - 8} bytes, the build wrote {size}")

    (path / "windows" / "start.memmap").unlink()
    reopen_expecting(rf"{path / 'windows' / 'start.memmap'} is missing")

    meta = path / cache.CACHE_META
    meta.write_text(meta.read_text()[:50])
    reopen_expecting(rf"{meta} is unreadable \(JSONDecodeError: .*\)")


UNGUARDED_SCRIPT = """
import multiprocessing
from pathlib import Path
from mmf_rl.datasets.cache import _locked

with _locked(Path({cache_dir!r})):  # no main guard: a spawned worker runs this again
    worker = multiprocessing.get_context("spawn").Process(target=print)
    worker.start()
    worker.join(timeout=120)
    print("worker exit code", worker.exitcode)
"""


@pytest.mark.slow
def test_a_worker_re_running_an_unguarded_script_is_refused_not_deadlocked(tmp_path):
    cache_dir = tmp_path / "cache"
    cache_dir.mkdir()
    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED_SCRIPT.format(cache_dir=str(cache_dir)))
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=240, cwd=tmp_path
    )
    assert "worker exit code 1" in done.stdout, done.stdout + done.stderr
    assert 'if __name__ == "__main__":' in done.stderr and str(script) in done.stderr
