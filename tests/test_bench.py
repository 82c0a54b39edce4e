"""`mmf-rl bench`: the benchmarks of benchmarks/ run from the CLI and end with their summary line."""

import os

import pytest

from benchmarks.synthetic.dataset import make_synthetic_dataset
from mmf_rl.bench import BENCHMARKS
from mmf_rl.cli import main as cli


def test_bench_data_runs_on_any_dataset_with_its_data_config(tmp_path, capsys):
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    root = tmp_path / "other"  # not the push features: the benchmark takes them from the data config
    make_synthetic_dataset(
        root, [24, 24, 24], image_size=32, nan_force_episodes=(), invalid_image_episodes=()
    )
    config = tmp_path / "mine.yaml"
    assert cli(["inspect", str(root), "--write-config", str(config)]) == 0
    capsys.readouterr()
    assert (
        cli(
            [
                "bench",
                "data",
                "--data-config",
                str(config),
                "--history",
                "4",
                "--horizon",
                "3",
                "--seconds",
                "0.2",
                "--batch-size",
                "8",
                "--lerobot-windows",
                "24",
                "--workers",
                "0",
            ]
        )
        == 0
    )
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("ratio: ") and "windows/s" in lines[-1]
    assert "front image [3, 32, 32]" in lines[-3] and "state sequence [4]" in lines[-3]


def test_bench_names_the_benchmarks_and_refuses_unknown_ones(capsys):
    assert cli(["bench", "--help"]) == 0
    out = capsys.readouterr().out
    for name in ("accuracy", "bc", "data", "model", "mpc"):
        assert f"\n  {name} " in out
    assert cli(["bench", "speed"]) == 2
    assert "invalid choice: 'speed'" in capsys.readouterr().err


@pytest.mark.parametrize("benchmark", ["data", "model", "mpc", "bc", "accuracy", "ethucy_calibration"])
def test_bench_passes_help_to_the_script(benchmark, capsys):
    assert cli(["bench", benchmark, "--help"]) == 0
    assert capsys.readouterr().out.startswith(f"usage: {BENCHMARKS[benchmark][0]}")  # runpy names the script
