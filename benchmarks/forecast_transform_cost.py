"""Per-step cost of `ForecastTransform` against the push env's own step, batch 1 and 16 envs.

    MUJOCO_GL=egl .venv/bin/python benchmarks/forecast_transform_cost.py [--steps 20] [--batches 1 16]

The forecaster is freshly initialised from the default model config (configs/model/forecaster.yaml)
with the push data's shape (configs/data/push.yaml: image 64x64, force, proprio, H = 10, T = 10,
D = 2), saved as a checkpoint and loaded with `ForecastTransform.from_checkpoint`: the real loading
path, untrained weights (the cost does not depend on them).

For each batch size, a `SerialEnv` of `MultimodalPushTorchEnv` is stepped with random actions
(timed: the env step, rendering included), and the recorded tensordicts are then fed to the
transform alone (timed: history update, normalisation, one batched forward, outputs), so the two
costs are measured separately in the same run: with the lean traced forward (the default,
``trace=True``) and with the eager TensorDict forward (``trace=False``), beside the eager model
forward alone. Medians over the timed steps; the reset before them traces the graphs.
`LatchedForecastTransform` (traced, its default rule) is timed on the same steps, and both
transforms again on the same steps with the camera lost from the middle on (the latch serves
then): its cost over the plain transform's in the same run.
Run it on a quiet machine: the figures are wall-clock times.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import torch
import yaml
from torchrl.envs import SerialEnv

from mmf_rl import keys
from mmf_rl.checkpoint import save_checkpoint
from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import build_model, saved_config
from mmf_rl.rl.latched_forecast import LatchedForecastTransform
from mmf_rl.rl.transforms import ForecastTransform

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def push_checkpoint(directory: Path) -> tuple[Path, dict]:
    data = yaml.safe_load((CONFIGS / "data" / "push.yaml").read_text())
    model_cfg = yaml.safe_load((CONFIGS / "model" / "forecaster.yaml").read_text())
    h, w = data["image_size"]
    specs = [
        ModalitySpec("image", "image", (3, h, w)),
        ModalitySpec("force", "sequence", (6,)),
        ModalitySpec("proprio", "sequence", (17,)),
    ]
    target_dim = len(data["target"]["dims"])
    torch.manual_seed(0)
    model = build_model(model_cfg, specs, data["history"], data["horizon"], target_dim)
    stats = {
        "force/mean": torch.zeros(6),
        "force/std": torch.ones(6),
        "proprio/mean": torch.zeros(17),
        "proprio/std": torch.ones(17),
        "target/mean": torch.zeros(target_dim),
        "target/std": torch.ones(target_dim),
    }
    path = save_checkpoint(
        directory,
        0,
        model.state_dict(),
        tensors=stats,
        meta={
            "model_config": saved_config(model_cfg.get("name", "forecaster"), model),
            "config": {"data": data},
        },
    )
    return path, data


def measure(num_envs: int, checkpoint: Path, image_size: int, steps: int, warmup: int) -> dict[str, float]:
    """Median seconds per step for ``num_envs`` envs: the env step, the transform (lean traced and
    eager forward) and the eager model forward alone."""
    env = SerialEnv(num_envs, MultimodalPushTorchEnv, create_env_kwargs={"image_size": image_size})
    try:
        env.set_seed(0)
        td = env.reset()
        reset = td.clone()
        frames, env_times = [], []
        for _ in range(warmup + steps):
            td = env.rand_action(td)
            start = time.perf_counter()
            out = env.step(td)
            env_times.append(time.perf_counter() - start)
            frames.append(out["next"].clone())
            td = env.step_mdp(out)  # rand actions rarely finish an episode in these few steps
    finally:
        env.close()

    times = {"env": env_times}
    for name, trace in (("lean", True), ("eager", False)):
        transform = ForecastTransform.from_checkpoint(checkpoint, trace=trace)
        transform._reset(reset.empty(), reset.clone())  # noqa: SLF001 - the transform alone, no env around it
        times[name], model_times = [], []
        for frame in frames:
            start = time.perf_counter()
            transform._call(frame)  # noqa: SLF001
            times[name].append(time.perf_counter() - start)
            if not trace:
                # The model alone on the same window: what is left is the transform's own bookkeeping.
                window = transform.window()
                with torch.inference_mode():
                    start = time.perf_counter()
                    transform.model(window)
                    model_times.append(time.perf_counter() - start)
        if model_times:
            times["model"] = model_times
    times["latched"] = time_steps(LatchedForecastTransform.from_checkpoint(checkpoint), reset, frames)
    outage = camera_lost_midway(frames)
    times["lean_outage"] = time_steps(ForecastTransform.from_checkpoint(checkpoint), reset, outage)
    times["latched_outage"] = time_steps(LatchedForecastTransform.from_checkpoint(checkpoint), reset, outage)
    return {name: statistics.median(values[warmup:]) for name, values in times.items()}


def time_steps(transform: ForecastTransform, reset, frames) -> list[float]:
    """Seconds of each of ``transform``'s steps on ``frames`` after a reset on ``reset``."""
    transform._reset(reset.empty(), reset.clone())  # noqa: SLF001 - the transform alone, no env around it
    seconds = []
    for frame in frames:
        start = time.perf_counter()
        transform._call(frame)  # noqa: SLF001
        seconds.append(time.perf_counter() - start)
    return seconds


def camera_lost_midway(frames: list) -> list:
    """``frames`` with the camera flagged absent in every env from the middle step on."""
    lost = [frame.clone() for frame in frames]
    for frame in lost[len(lost) // 2 :]:
        frame[keys.present_key("image")] = torch.zeros_like(frame[keys.present_key("image")])
    return lost


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=20, help="timed steps per batch size")
    parser.add_argument("--warmup", type=int, default=3, help="untimed first steps")
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args()
    if args.warmup < 1:
        parser.error("--warmup must be >= 1: TorchScript optimises a graph on its first runs")
    torch.set_num_threads(args.threads)

    with tempfile.TemporaryDirectory() as tmp:
        checkpoint, data = push_checkpoint(Path(tmp))
        image_size = data["image_size"][0]
        results = {b: measure(b, checkpoint, image_size, args.steps, args.warmup) for b in args.batches}

    print(
        f"forecaster: default config, image {image_size}x{image_size} + force 6 + proprio 17, "
        f"H={data['history']}, "
        f"T={data['horizon']}; {args.threads} threads; median of {args.steps} steps"
    )
    for b, r in results.items():
        print(
            f"batch {b:>3}: env step {r['env'] * 1e3:7.2f} ms, ForecastTransform {r['lean'] * 1e3:7.2f} ms "
            f"({r['lean'] / b * 1e3:.2f} ms/env; eager forward {r['eager'] * 1e3:.2f} ms, model forward "
            f"alone {r['model'] * 1e3:.2f} ms), transform/env = {r['lean'] / r['env']:.2f}"
        )
    for b, r in results.items():
        print(
            f"batch {b:>3}: LatchedForecastTransform {r['latched'] * 1e3:7.2f} ms "
            f"(+{(r['latched'] - r['lean']) * 1e3:.2f} ms, latched/plain = {r['latched'] / r['lean']:.2f}); "
            f"camera lost midway: latched "
            f"{r['latched_outage'] * 1e3:.2f} ms, plain {r['lean_outage'] * 1e3:.2f} ms (+"
            f"{(r['latched_outage'] - r['lean_outage']) * 1e3:.2f} ms, latched/plain = "
            f"{r['latched_outage'] / r['lean_outage']:.2f})"
        )
    # The first and the last batch size (once when they are the same, e.g. ``--batches 1``).
    parts = [
        f"batch{b} {results[b]['lean'] * 1e3:.2f} ms (eager {results[b]['eager'] * 1e3:.2f} ms, env step "
        f"{results[b]['env'] * 1e3:.2f} ms, transform/env {results[b]['lean'] / results[b]['env']:.2f})"
        for b in dict.fromkeys([args.batches[0], args.batches[-1]])
    ]
    print(f"summary: forecast per step: {', '.join(parts)}")


if __name__ == "__main__":
    main()
