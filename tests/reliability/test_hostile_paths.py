"""Paths in configs: eval writes outside its run only when asked; run names cannot traverse.

Checkpoints crafted to run code on load are refused: tests/trainers/test_checkpoint.py::
test_pickled_code_in_trainer_state_is_refused (weights are safetensors, never pickle).
"""

import json
import shutil
from pathlib import Path

import pytest
import yaml

from mmf_rl.cli import main as cli
from tests.conftest import push_train_overrides


@pytest.fixture
def trained_run(push_forecaster_run, tmp_path):
    """A copy of the session's tiny forecaster: the test evaluates into it."""
    return Path(shutil.copytree(push_forecaster_run, tmp_path / "run"))


def evaluate(run, *overrides) -> int:
    return cli(["eval", f"checkpoint={run}", "num_samples=2", "plots=false", *overrides])


def test_eval_writes_outside_its_run_directory_only_when_allowed(trained_run, tmp_path, capsys):
    elsewhere = tmp_path / "elsewhere"
    for out_dir in (elsewhere, trained_run / ".." / "escape"):
        assert evaluate(trained_run, f"out_dir={out_dir}") == 1
        err = capsys.readouterr().err
        assert err.startswith("mmf-rl eval: error:") and f"resolves to {out_dir.resolve()}" in err
        assert "outside the run directory" in err and "allow_outside_run_dir=true" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"], "a refused out_dir is not even created"

    assert evaluate(trained_run, f"out_dir={trained_run / 'eval_k2'}") == 0
    assert (trained_run / "eval_k2" / "results.json").is_file()
    assert evaluate(trained_run, f"out_dir={elsewhere}", "allow_outside_run_dir=true") == 0
    assert json.loads((elsewhere / "results.json").read_text())["checkpoint"].startswith(str(trained_run))


def test_relative_run_dir_with_dotdot_is_resolved_and_saved_resolved(
    recorded_push_root, push_cache_dir, tmp_path, monkeypatch, capsys
):
    cwd = tmp_path / "a" / "b"
    cwd.mkdir(parents=True)
    monkeypatch.chdir(cwd)
    assert (
        cli(["train", *push_train_overrides(recorded_push_root, push_cache_dir, "../../runs/x", steps=2)])
        == 0
    )
    resolved = (tmp_path / "runs" / "x").resolve()
    assert yaml.safe_load((resolved / "config.yaml").read_text())["run_dir"] == str(resolved)
    assert f"-> {resolved}" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["../../etc", "a/b", ".."])
def test_a_run_name_with_path_separators_is_refused(
    recorded_push_root, push_cache_dir, tmp_path, monkeypatch, capsys, name
):
    monkeypatch.chdir(tmp_path)
    overrides = [
        o
        for o in push_train_overrides(recorded_push_root, push_cache_dir, "unused")
        if not o.startswith("run_dir=")
    ]
    assert cli(["train", *overrides, f"name={name}"]) == 1
    err = capsys.readouterr().err
    assert f"name={name!r} must be a plain name without path separators" in err and "run_dir=PATH" in err
    assert list(tmp_path.iterdir()) == [], "nothing was written"
