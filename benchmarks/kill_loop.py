"""SIGKILL `mmf-rl train` at random steps, several times in a row, then resume it to the end.

    MUJOCO_GL=egl .venv/bin/python benchmarks/kill_loop.py [--kills 6] [--steps 60] [--seed 0]

Records a small push dataset (or reads ``--data``), trains an uninterrupted reference run, then
trains the same config in a subprocess that is SIGKILLed once it has checkpointed a random step,
resumed with ``resume=true``, killed again, ``--kills`` times, and finally resumed to the end.
After every kill, every ``step_*`` directory under ``checkpoints/`` must load (weights, tensors
and trainer state): a kill never leaves a half-written checkpoint. At the end the weights must
equal the reference's (rtol 1e-5, atol 1e-6). Every training runs in a single-threaded
subprocess, so the two runs use the same kernels. Prints one line per kill and a verdict; exits 1
on a failure.
"""

from __future__ import annotations

import argparse
import os
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from safetensors.torch import load_file

from mmf_rl.checkpoint import CheckpointError, load_checkpoint

REPO = Path(__file__).resolve().parent.parent

POLL_S = 0.02


def subprocess_env() -> dict[str, str]:
    """The environment of a training subprocess: this repository importable, one thread."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    env["OMP_NUM_THREADS"] = "1"
    env.setdefault("HF_HUB_OFFLINE", "1")
    env.setdefault("MUJOCO_GL", "egl")
    return env


def train_command(overrides: list[str]) -> list[str]:
    return [sys.executable, "-m", "mmf_rl.cli", "train", *overrides]


def checkpoint_steps(checkpoints: Path) -> list[int]:
    """Steps of the ``step_*`` directories, each loaded in full; raises on one that does not load."""
    steps = []
    for path in sorted(checkpoints.glob("step_*")):
        try:
            steps.append(load_checkpoint(path).step)
        except CheckpointError as error:
            raise AssertionError(f"{path} does not load after a kill: {error}") from None
    return steps


def kill_when_checkpointed(overrides: list[str], checkpoints: Path, step: int, timeout_s: float = 600) -> int:
    """Run `mmf-rl train` until it has checkpointed ``step`` or later, SIGKILL it; return the newest step."""
    log = tempfile.TemporaryFile("w+")  # noqa: SIM115 - a file, not a pipe (a full pipe would block the run)
    process = subprocess.Popen(
        train_command(overrides), env=subprocess_env(), stdout=subprocess.DEVNULL, stderr=log
    )
    try:
        deadline = time.monotonic() + timeout_s
        while not any(int(p.name.split("_")[1]) >= step for p in checkpoints.glob("step_*")):
            if process.poll() is not None:
                log.seek(0)
                raise AssertionError(
                    f"training ended (exit {process.returncode}) before step {step} could be "
                    f"killed:\n{log.read()[-3000:]}"
                )
            if time.monotonic() > deadline:
                raise AssertionError(f"no checkpoint of step {step} after {timeout_s} s")
            time.sleep(POLL_S)
        process.kill()  # SIGKILL: no cleanup, no final checkpoint; it may be writing one right now
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        log.close()
    return max(checkpoint_steps(checkpoints))


def kill_repeatedly(
    overrides: list[str], checkpoints: Path, kills: int, total_steps: int, rng: random.Random
) -> list[int]:
    """Start the run, then kill it ``kills`` times at random steps, resuming after each kill.

    Returns the newest checkpointed step after each kill. The run must checkpoint every step.
    """
    newest = 0
    killed_at = []
    for kill in range(kills):
        remaining = kills - kill
        # Leave room for the kills still to come and for the final resume.
        step = rng.randint(newest + 1, newest + max(1, (total_steps - 1 - newest) // remaining))
        newest = kill_when_checkpointed([*overrides, *(["resume=true"] if kill else [])], checkpoints, step)
        if newest >= total_steps:
            raise AssertionError(
                f"kill {kill + 1} came after the run finished (step {newest}); use more steps"
            )
        killed_at.append(newest)
    return killed_at


def final_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_file(load_checkpoint(run_dir / "checkpoints").path / "model.safetensors")


def weights_match(reference: dict[str, torch.Tensor], other: dict[str, torch.Tensor]) -> tuple[bool, float]:
    """Whether two state dicts agree within rtol 1e-5, atol 1e-6, and their largest absolute gap."""
    assert reference.keys() == other.keys(), sorted(set(reference) ^ set(other))
    ok = all(torch.allclose(other[k], v, rtol=1e-5, atol=1e-6) for k, v in reference.items())
    return ok, max(float((reference[k] - other[k]).abs().max()) for k in reference)


def run_overrides(data: Path, cache_dir: Path, run_dir: Path, total_steps: int) -> list[str]:
    """A tiny forecaster on a small push recording, checkpointed every step, never validated."""
    return [
        f"data.root={data}",
        f"data.cache_dir={cache_dir}",
        f"run_dir={run_dir}",
        "data.image_size=[32,32]",
        "data.history=4",
        "data.horizon=3",
        "data.split_fractions=[0.5,0.25,0.25]",
        "model.d_model=16",
        "model.d_latent=4",
        "model.num_heads=2",
        "model.mlp_hidden=32",
        "model.head_hidden=32",
        f"trainer.total_steps={total_steps}",
        "trainer.batch_size=16",
        "trainer.log_every=2",
        "trainer.checkpoint_every=1",
        "trainer.eval_every=100000",
        "trainer.warmup_steps=2",
        "trainer.progress_bar=false",
        "logger=csv",
        "num_workers=0",
    ]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=6)
    parser.add_argument(
        "--steps", type=int, default=60, help="total training steps (one checkpoint per step)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seeds the kill steps")
    parser.add_argument("--data", type=Path, help="a push dataset; default: record a small one")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    with tempfile.TemporaryDirectory(prefix="mmf-rl-kill-loop-") as tmp:
        tmp = Path(tmp)
        data = args.data
        if data is None:
            from mmf_rl.record import RecordConfig, record

            data = record(RecordConfig(out=tmp / "push", episodes=6, steps=40, image_size=32, seed=3))
        started = time.perf_counter()
        reference = run_overrides(data, tmp / "cache", tmp / "reference", args.steps)
        subprocess.run(train_command(reference), env=subprocess_env(), check=True, stdout=subprocess.DEVNULL)
        killed_dir = tmp / "killed"
        killed = run_overrides(data, tmp / "cache", killed_dir, args.steps)
        killed_at = kill_repeatedly(killed, killed_dir / "checkpoints", args.kills, args.steps, rng)
        for number, step in enumerate(killed_at, 1):
            print(f"kill {number}: SIGKILL after checkpoint step {step}; every step_* checkpoint loads")
        subprocess.run(
            train_command([*killed, "resume=true"]),
            env=subprocess_env(),
            check=True,
            stdout=subprocess.DEVNULL,
        )
        ok, gap = weights_match(final_weights(tmp / "reference"), final_weights(killed_dir))
        leftovers = list((killed_dir / "checkpoints").glob(".step_*"))
        print(
            f"{args.kills} kills, {args.steps} steps, {time.perf_counter() - started:.0f} s; "
            f"max |w_resumed - w_reference| = {gap:.3g}; temp dirs left by kills: {len(leftovers)}"
        )
        print(
            "verdict: PASS, resumed weights equal the uninterrupted run's"
            if ok
            else "verdict: FAIL, resumed weights differ from the uninterrupted run's"
        )
        return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
