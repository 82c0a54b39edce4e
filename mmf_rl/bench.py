"""`mmf-rl bench accuracy|bc|calibration|data|ethucy|ethucy_calibration|humanoid|latch|model|mpc|mult_gap|
robust_training|step_cost [args]`: the scripts of command line.

Each runs ``benchmarks/<script>.py`` of the repository checkout with the arguments that follow
(``mmf-rl bench data --help`` shows them) and ends with that script's summary line. The scripts
ship with the repository, not with the package: a wheel install has none. The comparison protocol
of ``accuracy`` ships with the package: ``mmf-rl compare`` runs it on any data config.
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

BENCHMARKS_DIR = Path(__file__).resolve().parents[1] / "benchmarks"
# name -> (script, what it measures)
BENCHMARKS = {
    "accuracy": ("accuracy.py", "the paper's table on the push data: every model and missingness protocol"),
    "data": ("data_throughput.py", "windows/s of the window cache vs lerobot's loader, on any dataset"),
    "model": ("model_throughput.py", "training samples/s and inference latency of the forecaster"),
    "mpc": ("mpc_push.py", "MPC with the push world model vs the scripted pusher and a random policy"),
    "bc": ("bc_push.py", "behaviour cloning with vs without the forecast, camera or force off"),
    "latch": (
        "latched_forecast_outage.py",
        "latched vs fresh forecasts of a trained run through a camera outage",
    ),
    "humanoid": ("real_humanoid.py", "the paper model vs the baselines on the real G1 humanoid recording"),
    "calibration": (
        "calibration.py",
        "interval coverage of trained runs under each eval latent, recalibrated",
    ),
    "step_cost": ("step_cost.py", "training-step cost of forecaster variants against MulT, side by side"),
    "mult_gap": ("mult_gap.py", "hybrids of MulT and the paper model: where MulT's all-sensor lead is from"),
    "robust_training": (
        "robust_training.py",
        "architecture x training for missing sensors; the forecaster best in every subset, chosen on val",
    ),
    "ethucy": ("ethucy.py", "ETH/UCY pedestrians, 5 leave-one-scene-out folds: minADE20/minFDE20 in metres"),
    "ethucy_calibration": (
        "ethucy_calibration.py",
        "ETH/UCY: interval coverage on the held-out scene, fitted on val or on held-out training scenes",
    ),
}
EXAMPLES = [
    "mmf-rl bench model --steps 5",
    "mmf-rl bench data --root /data/mine --data-config mine.yaml   # your dataset, your data config",
    "mmf-rl bench accuracy --quick",
    "mmf-rl compare data=/path/to/mine.yaml      # the accuracy protocol on your data (installed package)",
    "mmf-rl bench ethucy --quick --data data/ethucy --out runs/bench_ethucy_quick",
]


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="mmf-rl bench",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="benchmarks:\n"
        + "\n".join(f"  {name:<12} {what}" for name, (_, what) in BENCHMARKS.items())
        + "\n\nexamples:\n"
        + "\n".join(f"  {example}" for example in EXAMPLES),
    )
    parser.add_argument("benchmark", choices=sorted(BENCHMARKS), help="which benchmark")
    parser.add_argument(
        "args", nargs=argparse.REMAINDER, help="the benchmark's own arguments (see BENCHMARK --help)"
    )
    return parser.parse_args(argv)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    script = BENCHMARKS_DIR / BENCHMARKS[args.benchmark][0]
    if not script.is_file():
        print(
            f"mmf-rl bench: error: {script} does not exist; the benchmarks ship with the repository, not the "
            "package: run this from a clone of mmf-rl (git clone, then `make setup`)",
            file=sys.stderr,
        )
        return 1
    saved = sys.argv
    sys.argv = [str(script), *args.args]
    try:
        # The scripts are written for `python benchmarks/X.py`: run them exactly so.
        runpy.run_path(str(script), run_name="__main__")
    finally:
        sys.argv = saved
    return 0
