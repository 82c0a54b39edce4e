"""mmf_rl.compare.script: the flags, modes, push recording and result files the comparison scripts
share (one pass of the protocol runs in tests/compare/test_command.py and the benchmark tests)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from mmf_rl.compare import entries, script

TINY = script.Mode(image_size=32, batch_size=8, steps=4, seeds=(0, 1), entries=("paper",), episodes=16)


def parser_of(*override_flags: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="bench")
    script.add_override_flags(parser, *override_flags)
    parser.add_argument("--entries", nargs="+", default=None)
    script.add_run_flags(parser)
    return parser


def test_flags_given_replace_the_modes_values_and_the_others_keep_them():
    parser = parser_of("seeds", "steps", "batch-size")
    args = parser.parse_args(["--seeds", "3", "4", "--entries", "paper", "MulT"])
    mode = TINY.overridden(args)
    assert mode == script.Mode(32, 8, 4, (3, 4), ("paper", "MulT"), 16)
    assert TINY.overridden(parser.parse_args(["--steps", "7", "--batch-size", "2"])).budget == entries.Budget(
        steps=7, batch_size=2, seeds=(0, 1), image_size=32
    )
    assert (args.device, args.jobs) == ("cpu", 1)


def test_bad_run_flags_are_usage_errors_naming_the_flag(capsys):
    parser = parser_of("seeds")
    with pytest.raises(SystemExit) as exit_:
        script.check_run_flags(parser, parser.parse_args(["--jobs", "0"]))
    assert exit_.value.code == 2 and "--jobs must be >= 1, found 0" in capsys.readouterr().err
    args = parser.parse_args(["--entries", "paper", "Mult"])
    with pytest.raises(SystemExit):
        script.check_run_flags(parser, args, entries.CATALOGUE)
    assert "--entries: unknown ['Mult']; the entries are ['paper'," in capsys.readouterr().err
    without_paper = parser.parse_args(["--entries", "MulT"])
    with pytest.raises(SystemExit):
        script.check_run_flags(parser, without_paper, entries.CATALOGUE)
    assert "'paper' missing" in capsys.readouterr().err
    script.check_run_flags(parser, without_paper, entries.CATALOGUE, paper_required=False)
    script.check_run_flags(parser, args)  # without a catalogue --entries is left to the caller


def test_a_push_study_trains_the_modes_entries_on_the_recording(tmp_path):
    args = argparse.Namespace(budget=TINY, data=tmp_path / "push", out=tmp_path / "out", device="cpu", jobs=2)
    study = script.push_study(args, entries.CATALOGUE, ["force", "image", "proprio"])
    assert [e.label for e in study.entries] == ["paper"]
    assert study.budget == entries.Budget(steps=4, batch_size=8, seeds=(0, 1), image_size=32)
    assert study.data_overrides == (f"data.root={tmp_path / 'push'}",) and study.jobs == 2
    assert script.push_recording_path(Path("/repo"), 200) == Path("/repo/data/push_bench_200ep")


def test_the_push_recording_is_made_only_when_absent(tmp_path, monkeypatch):
    made = []
    monkeypatch.setattr(script.subprocess, "run", lambda command, **_: made.append(command))
    absent = script.PushRecording(tmp_path / "push", 16)
    assert absent.make_if_absent() >= 0.0
    assert made[0][1:4] == ["-m", "mmf_rl.cli", "record"]
    options = " ".join(made[0][4:])
    assert (
        options == f"--out {tmp_path / 'push'} --episodes 16 --workers 2 --image-size 64 --steps 50 --seed 0"
    )
    (tmp_path / "push").mkdir()
    assert absent.make_if_absent() is None and len(made) == 1
    assert script.recorded_episodes(tmp_path / "push") is None
    (tmp_path / "push" / "meta").mkdir()
    (tmp_path / "push" / "meta" / "info.json").write_text(json.dumps({"total_episodes": 16}))
    assert script.recorded_episodes(tmp_path / "push") == 16


def test_the_results_are_written_into_a_new_out_directory_and_printed(tmp_path, capsys):
    script.report_results(tmp_path / "a" / "out", "# report\nsummary: x\n", {"summary": {"x": 1}})
    assert capsys.readouterr().out == "# report\nsummary: x\n"
    assert (tmp_path / "a" / "out" / "results.md").read_text() == "# report\nsummary: x\n"
    assert json.loads((tmp_path / "a" / "out" / "results.json").read_text()) == {"summary": {"x": 1}}


def test_a_study_that_cannot_run_stops_the_script_with_its_title(tmp_path):
    bad = entries.Entry("paper", "paper", ("model=forecaster", "model.fusoin=sum"))
    study = entries.Study(
        out=tmp_path, budget=TINY.budget, entries=(bad,), modalities=("force", "image", "proprio")
    )
    with pytest.raises(SystemExit, match="^mult_gap benchmark: these entries do not compose"):
        script.check_study(study, "mult_gap benchmark")
