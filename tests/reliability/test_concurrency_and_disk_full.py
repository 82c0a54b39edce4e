"""Two trainers on one dataset, a read during a rebuild, a full disk, and what a kill leaves behind."""

import errno

import pytest
import torch

from mmf_rl import checkpoint as checkpoint_module
from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import WindowDataset, cache
from tests.conftest import push_train_overrides
from tests.reliability.conftest import (
    background,
    cli_command,
    edit_frames,
    output,
    push_data_config,
    wait_for,
)

DECODING = "decoding cameras into the window cache"


def test_two_trainers_on_one_dataset_build_the_cache_once_and_both_train(recorded_push_root, tmp_path):
    cache_dir = tmp_path / "cache"
    runs = [tmp_path / "a", tmp_path / "b"]
    with (
        background(
            cli_command("train", *push_train_overrides(recorded_push_root, cache_dir, runs[0], steps=2))
        ) as a,
        background(
            cli_command("train", *push_train_overrides(recorded_push_root, cache_dir, runs[1], steps=2))
        ) as b,
    ):
        for process in (a, b):
            wait_for(lambda p=process: p.poll() is not None, process, 600, "the end of training")
    outputs = [output(a), output(b)]
    assert a.returncode == 0 and b.returncode == 0, outputs
    assert sum(DECODING in out for out in outputs) == 1, "exactly one process decoded the videos"
    assert len([p for p in cache_dir.iterdir()]) == 1, "one cache, no leftover build"
    assert all(load_checkpoint(run / "checkpoints").step == 2 for run in runs)


def change_one_force_value(frames) -> None:
    frames.at[0, "observation.force"][0] += 1.0


def test_a_reader_during_a_rebuild_after_a_dataset_change_waits_for_the_complete_cache(push_copy, tmp_path):
    cache_dir = tmp_path / "cache"
    old = WindowDataset(push_data_config(push_copy, cache_dir))
    before = old.batch(torch.arange(len(old)))
    edit_frames(push_copy, change_one_force_value)  # a new fingerprint: a new cache directory
    script = (
        "import sys; from mmf_rl.datasets import WindowDataset; from tests.reliability.conftest import "
        f"push_data_config; WindowDataset(push_data_config({str(push_copy)!r}, {str(cache_dir)!r}), "
        "num_workers=1)"
    )
    with background([cli_command()[0], "-c", script]) as builder:
        wait_for(lambda: any(cache_dir.glob(".building-*")), builder, 300, "a build in progress")
        reader = WindowDataset(push_data_config(push_copy, cache_dir))  # blocks until the build is complete
        assert not reader.built, "the reader waited for the other process's build instead of building its own"
        assert cache.cache_damage(reader.cache_path) is None
        wait_for(lambda: builder.poll() is not None, builder, 300, "the end of the build")
    assert builder.returncode == 0, output(builder)
    assert reader.cache_path != old.cache_path and old.cache_path.is_dir(), "the old cache is left as it was"
    after = old.batch(torch.arange(len(old)))
    assert all(torch.equal(before.get(k), after.get(k)) for k in before.keys(True, True))


def enospc(*args, **kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_during_a_cache_build_removes_the_partial_build_and_says_so(
    push_copy, tmp_path, monkeypatch
):
    cache_dir = tmp_path / "cache"
    previous = WindowDataset(push_data_config(push_copy, cache_dir, history=3)).cache_path
    monkeypatch.setattr(cache, "_file_records", enospc)  # the last files of the build
    with pytest.raises(
        OSError,
        match=r"no space left on device while building the window cache .*the partial "
        r"build was removed, nothing else changed: free space in .*data.cache_dir",
    ):
        WindowDataset(push_data_config(push_copy, cache_dir))
    assert [p.name for p in cache_dir.iterdir()] == [previous.name] and cache.cache_damage(previous) is None


def test_a_cache_larger_than_the_free_space_is_refused_before_writing(push_copy, tmp_path, monkeypatch):
    cache_dir = tmp_path / "cache"
    cache_dir.mkdir()
    monkeypatch.setattr(cache.shutil, "disk_usage", lambda path: type("Usage", (), {"free": 2**20})())
    with pytest.raises(
        OSError,
        match=r"the window cache of .* needs about [\d.]+ GiB \(\d+ frames\) in .*, which "
        r"has 0.00 GiB free; .*\(nothing was written\)",
    ):
        WindowDataset(push_data_config(push_copy, cache_dir))
    assert list(cache_dir.iterdir()) == []


def logged_steps(run, name="train/loss") -> list[int]:
    return [
        int(line.split(",")[0])
        for line in (run / "logs" / "scalars" / f"{name}.csv").read_text().splitlines()
    ]


def test_disk_full_during_a_checkpoint_save_keeps_the_previous_one_then_resume_logs_each_step_once(
    recorded_push_root, push_cache_dir, tmp_path, monkeypatch, capsys
):
    run = tmp_path / "run"
    overrides = push_train_overrides(
        recorded_push_root, push_cache_dir, run, steps=6
    )  # checkpoints at 3 and 6
    real_save_file, calls = checkpoint_module.save_file, []

    def fills_the_disk_at_step_6(tensors, path):
        calls.append(path)
        if ".step_000000006." in str(path):
            enospc()
        return real_save_file(tensors, path)

    monkeypatch.setattr(checkpoint_module, "save_file", fills_the_disk_at_step_6)
    assert cli(["train", *overrides]) == 1
    err = capsys.readouterr().err
    assert "mmf-rl train: error: no space left on device while saving checkpoint step 6 in " in err
    assert f"the previous checkpoint {run / 'checkpoints' / 'step_000000003'} is intact" in err
    assert "resume=true" in err
    assert [p.name for p in list_checkpoints(run / "checkpoints")] == ["step_000000003"]
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["last", "step_000000003"], (
        "no temp files"
    )
    assert load_checkpoint(run / "checkpoints").step == 3
    assert logged_steps(run) == [2, 4, 6], "steps 4 and 6 were logged before the save failed"

    with open(run / "logs" / "scalars" / "train" / "loss.csv", "a") as log:
        log.write("3,0.")  # and a row cut short by a kill mid-write
    monkeypatch.undo()
    assert cli(["train", *overrides, "resume=true"]) == 0
    assert load_checkpoint(run / "checkpoints").step == 6
    # The resumed run logged 4 and 6 again: the rows after step 3 were dropped at resume.
    assert logged_steps(run) == [2, 4, 6]
    assert logged_steps(run, "train/lr") == [2, 4, 6]


def test_leftovers_of_a_killed_save_or_prune_are_removed_on_the_next_start(
    recorded_push_root, push_cache_dir, tmp_path, capsys
):
    run = tmp_path / "run"
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, run, steps=3)
    assert cli(["train", *overrides]) == 0
    checkpoints = run / "checkpoints"
    # What save_checkpoint leaves when killed mid-save (temp dir, pointer) or mid-prune (renamed old one).
    leftovers = [checkpoints / ".step_000000006.k2j4_1.tmp", checkpoints / ".step_000000001.x8fh2a.deleting"]
    for directory in leftovers:
        directory.mkdir()
        (directory / "model.safetensors").write_bytes(b"partial")
    (checkpoints / ".last.tmp").write_text("step_000000006\n")
    assert cli(["train", *overrides, "resume=true"]) == 0
    err = capsys.readouterr().err
    assert all(f"removed {path}" in err for path in [*leftovers, checkpoints / ".last.tmp"]), err
    assert sorted(p.name for p in checkpoints.iterdir()) == ["last", "step_000000003"]
