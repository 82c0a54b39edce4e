"""`mmf-rl compare` from an installed wheel: no repository checkout, any data config."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.benchmarks.conftest import study_out

REPO = Path(__file__).resolve().parents[2]
SUMMARY = re.compile(
    r"summary: all sensors paper MSE (\S+) vs best baseline (\S+) \((.+)\): paper/best = (\S+) "
    r"\(target <= 1\.05\); mean degradation without a sensor paper (\S+), best baseline (\S+)"
)
RUN_STARTS = "--- the run starts ---"


def installed_wheel(tmp: Path) -> Path:
    """Build the wheel from a copy of the sources (the build leaves the checkout alone) with uv, which
    the README's setup installs, and install it without dependencies (the venv has them) into a
    directory of its own; returns that directory."""
    source = tmp / "source"
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info")
    shutil.copytree(REPO / "mmf_rl", source / "mmf_rl", symlinks=True, ignore=ignore)
    shutil.copytree(REPO / "configs", source / "configs", ignore=ignore)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, source / name)
    env = {**os.environ, "UV_OFFLINE": "1"}
    build = ["uv", "build", "--wheel", "--no-build-isolation", "--python", sys.executable]
    subprocess.run([*build, "-o", str(tmp / "dist"), str(source)], check=True, env=env, capture_output=True)
    (wheel,) = (tmp / "dist").glob("mmf_rl-*.whl")
    site = tmp / "site"
    install = ["uv", "pip", "install", "--no-deps", "--python", sys.executable, "--target", str(site)]
    subprocess.run([*install, str(wheel)], check=True, env=env, capture_output=True)
    return site


@pytest.mark.skipif(shutil.which("uv") is None, reason="uv (installed by `make setup`) is not on PATH")
def test_compare_runs_from_an_installed_wheel_on_a_recorded_dataset(
    recorded_push_root, push_cache_dir, tmp_path
):
    site = installed_wheel(tmp_path)
    env = {k: v for k, v in os.environ.items() if not k.startswith("MMF_RL_")}
    env.update(PYTHONPATH=str(site), OMP_NUM_THREADS="1", HF_HUB_OFFLINE="1")
    work = tmp_path / "elsewhere"
    work.mkdir()
    # The run's window cache (out/cache) is the session's: the recording's windows at this config are
    # built once for every test that reads them.
    out = study_out(work, push_cache_dir)
    data = [
        f"data.root={recorded_push_root}",
        "data.history=4",
        "data.horizon=3",
        "data.split_fractions=[0.5,0.25,0.25]",
    ]
    budget = ["--entries", "paper", "LF-LSTM", "--seeds", "0", "--steps", "2", "--batch-size", "8"]
    argv = ["compare", *data, *budget, "--image-size", "32", "--out", "out"]
    # One process (each start imports torch): where the package and its configs come from, `mmf-rl
    # compare --help`, then the run as `python -m mmf_rl.cli compare ...` starts it (runpy runs the
    # module as __main__, as -m does; the module imported for the help is dropped first, as in a fresh
    # process).
    probe = (
        "import runpy, sys, mmf_rl.compare, mmf_rl.configuration as c\n"
        "print(mmf_rl.compare.__file__, c.config_dir())\n"
        "from mmf_rl.cli import main\n"
        "try:\n"
        "    main(['compare', '--help'])\n"
        "except SystemExit as end:\n"
        "    assert end.code in (0, None), end.code\n"
        f"print({RUN_STARTS!r}, flush=True)\n"
        "del sys.modules['mmf_rl.cli']\n"
        f"sys.argv = ['mmf_rl.cli', *{argv!r}]\n"
        "runpy.run_module('mmf_rl.cli', run_name='__main__', alter_sys=True)\n"
    )
    cmd = [sys.executable, "-c", probe]
    run = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    usage, stdout = run.stdout.split(f"{RUN_STARTS}\n", 1)
    where, help_text = usage.split("\n", 1)
    assert all(Path(p).is_relative_to(site) for p in where.split()), where  # the wheel, not the checkout
    assert "'LF-LSTM (retrained)'" in help_text and "data=" in help_text
    line = stdout.strip().splitlines()[-1]
    assert SUMMARY.fullmatch(line), line
    assert (out / "results.md").read_text().strip().splitlines()[-1] == line
    results = json.loads((out / "results.json").read_text())
    assert set(results["cells"]) == {"paper", "LF-LSTM"} and len(results["subsets"]) == 7
    assert (out / "paper" / "seed0" / "eval" / "window_errors.json").is_file()


def test_bad_arguments_are_clear_errors_before_any_training(tmp_path, capsys):
    from mmf_rl.cli import main as cli

    out = tmp_path / "out"
    assert cli(["compare", "--entries", "paper", "Mult", "--out", str(out)]) == 1
    assert "entries: unknown ['Mult']" in capsys.readouterr().err
    assert cli(["compare", "--entries", "MulT", "--out", str(out)]) == 1
    assert "'paper' missing" in capsys.readouterr().err
    assert cli(["compare", "model.fusoin=sum", "--out", str(out)]) == 1
    assert "model.fusoin" in capsys.readouterr().err
    assert cli(["compare", "--jobs", "0"]) == 2
    assert "--jobs must be >= 1" in capsys.readouterr().err
    assert not out.exists()
