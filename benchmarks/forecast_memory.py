"""Memory of `ForecastTransform` over a long run: 16 envs, 10k steps, resident set size must stay flat.

    .venv/bin/python benchmarks/forecast_memory.py [--steps 10000] [--envs 16] [--limit-mb 8]

The transform is driven directly with synthetic observation tensordicts shaped like the push
env's (image uint8 ``[3, 48, 48]``, force ``[6]``, proprio ``[17]``, a presence flag each),
fresh tensors every step as an env emits them, so 10k steps take minutes instead of the hours
16 MuJoCo envs would need. Presence flags flip at random (windows with and without each
modality, some with none) and a random subset of envs resets every 50 steps, so every path of
the transform runs. The model is a small, freshly initialised forecaster (H = 10, T = 10,
D = 2, image 32x32: frames are resized), with ``num_samples=3``.

RSS is read from ``/proc/self/statm``. Prints RSS at the start, after warm-up, at the end and its
peak, then a verdict: PASS when the growth after warm-up stays under ``--limit-mb``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import build_model
from mmf_rl.rl.transforms import ForecastTransform

PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")
FRAME_SIZE = 48
VECTOR_DIMS = {"force": 6, "proprio": 17}
SPECS = [
    ModalitySpec("image", "image", (3, 32, 32)),
    ModalitySpec("force", "sequence", (6,)),
    ModalitySpec("proprio", "sequence", (17,)),
]
RESET_EVERY = 50


def rss_bytes() -> int:
    """Resident set size of this process (second field of /proc/self/statm, in pages)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * PAGE_BYTES


def small_transform(seed: int = 0) -> ForecastTransform:
    torch.manual_seed(seed)
    model = build_model(
        {
            "name": "forecaster",
            "d_model": 32,
            "d_latent": 8,
            "num_heads": 2,
            "mlp_hidden": 64,
            "head_hidden": 64,
        },
        SPECS,
        history=10,
        horizon=10,
        target_dim=2,
    )
    stats = {"target/mean": torch.zeros(2), "target/std": torch.ones(2)}
    for name, dim in VECTOR_DIMS.items():
        stats[f"{name}/mean"], stats[f"{name}/std"] = torch.zeros(dim), torch.ones(dim)
    return ForecastTransform(model, stats, num_samples=3)


def observation(num_envs: int, generator: torch.Generator) -> TensorDict:
    """One step of ``num_envs`` envs: fresh tensors, each modality absent in ~20% of the envs."""
    obs = {
        "image": torch.randint(
            0, 256, (num_envs, 3, FRAME_SIZE, FRAME_SIZE), dtype=torch.uint8, generator=generator
        )
    }
    obs |= {name: torch.randn(num_envs, dim, generator=generator) for name, dim in VECTOR_DIMS.items()}
    present = {name: torch.rand(num_envs, generator=generator) > 0.2 for name in obs}
    return TensorDict({keys.OBS: obs, keys.PRESENT: present}, batch_size=[num_envs])


def drive(
    transform: ForecastTransform, num_envs: int, steps: int, seed: int = 0, on_step=lambda step: None
) -> None:
    """Reset every env, then ``steps`` steps with a random partial reset every `RESET_EVERY` steps."""
    generator = torch.Generator().manual_seed(seed)
    first = observation(num_envs, generator)
    transform._reset(first.empty(), first)  # noqa: SLF001 - the transform alone, no env around it
    for step in range(1, steps + 1):
        if step % RESET_EVERY == 0:
            reset = TensorDict(
                {"_reset": torch.rand(num_envs, 1, generator=generator) < 0.3}, batch_size=[num_envs]
            )
            out = transform._reset(reset, observation(num_envs, generator))  # noqa: SLF001
        else:
            out = transform._call(observation(num_envs, generator))  # noqa: SLF001
        assert out.get(keys.FORECAST_LOC).shape == (num_envs, 10, 2)
        on_step(step)


def measure(num_envs: int, steps: int, warmup: int, sample_every: int = 50) -> dict[str, int]:
    """RSS (bytes) at the start, after ``warmup`` steps, at the end, and its peak over sampled steps."""
    transform = small_transform()
    readings = {"start": rss_bytes()}
    peak = readings["start"]

    def sample(step: int) -> None:
        nonlocal peak
        if step == warmup:
            readings["warm"] = rss_bytes()
        if step % sample_every == 0:
            peak = max(peak, rss_bytes())

    with torch.no_grad():
        drive(transform, num_envs, warmup + steps, on_step=sample)
    readings["end"] = rss_bytes()
    readings["peak"] = max(peak, readings["end"])
    return readings


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10_000, help="steps measured after the warm-up")
    parser.add_argument("--warmup", type=int, default=200)
    parser.add_argument("--envs", type=int, default=16)
    parser.add_argument(
        "--limit-mb", type=float, default=8.0, help="largest RSS growth after warm-up that passes"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    started = time.perf_counter()
    rss = measure(args.envs, args.steps, args.warmup)
    elapsed = time.perf_counter() - started
    mib = {k: v / 2**20 for k, v in rss.items()}
    growth = mib["end"] - mib["warm"]
    print(
        f"{args.envs} envs, {args.warmup} warm-up + {args.steps} steps in {elapsed:.0f} s "
        f"({1000 * elapsed / (args.warmup + args.steps):.1f} ms/step)"
    )
    print(
        f"RSS start {mib['start']:.1f} MiB, after warm-up {mib['warm']:.1f} MiB, end {mib['end']:.1f} MiB, "
        f"peak {mib['peak']:.1f} MiB; growth after warm-up {growth:+.2f} MiB"
    )
    ok = growth < args.limit_mb
    print(f"verdict: {'PASS' if ok else 'FAIL'}, growth {'<' if ok else '>='} {args.limit_mb} MiB")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
