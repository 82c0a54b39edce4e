"""Training throughput and inference latency of a model (default: the forecaster) on a push-like batch.

    .venv/bin/python benchmarks/model_throughput.py [--batch-size 256] [--steps 10] [--profile]
    .venv/bin/python benchmarks/model_throughput.py --model mult --image-size 32 --batch-size 32
    .venv/bin/python benchmarks/model_throughput.py --channels-last     # a candidate speed-up, same numbers

The batch is what the push benchmark feeds the model: a 64x64 RGB window (``--image-size``),
force (6-D) and proprioception (20-D) sequences, H = 10, T = 10, D = 2, with a mix of presence
patterns. ``--model`` picks any registered model with its ``configs/model/<name>.yaml`` and the
default loss config (what ``benchmarks/accuracy.py`` trains). The achieved GFLOP/s (FLOPs counted
by ``torch.utils.flop_counter`` for one step) is printed as a fraction of an fp32 matmul peak
measured in the same run on the same threads.

Speed-up candidates, off by default, to compare on a quiet machine against a run without them:
``--channels-last`` stores the ConvNets' weights NHWC, so oneDNN runs the convolutions in that
layout (same forecasts and gradients: tests/test_model_throughput.py); ``--compile`` wraps the
loss module in ``torch.compile`` (the first steps, excluded from the timing, pay the compilation).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict import TensorDict
from torch.utils.flop_counter import FlopCounterMode

from mmf_rl import keys
from mmf_rl.configuration import compose_config, to_container
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import MODELS, build_loss, build_model
from mmf_rl.objectives import LossConfig


def push_modalities(image_size: int = 64) -> list[ModalitySpec]:
    return [
        ModalitySpec("image", "image", (3, image_size, image_size)),
        ModalitySpec("force", "sequence", (6,)),
        ModalitySpec("proprio", "sequence", (20,)),
    ]


PUSH_MODALITIES = push_modalities()


def push_like_batch(
    batch_size: int, history: int = 10, horizon: int = 10, seed: int = 0, image_size: int = 64
) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    data = {
        keys.obs_key("image"): torch.randint(
            0, 256, (batch_size, history, 3, image_size, image_size), generator=g, dtype=torch.uint8
        ),
        keys.obs_key("force"): torch.randn(batch_size, history, 6, generator=g),
        keys.obs_key("proprio"): torch.randn(batch_size, history, 20, generator=g),
        keys.TARGET: torch.randn(batch_size, horizon, 2, generator=g),
    }
    # Mostly complete samples, some with one sensor out: the mix the model trains on.
    for spec in PUSH_MODALITIES:
        data[spec.present_key] = torch.rand(batch_size, generator=g) > 0.15
    data[keys.present_key("proprio")] |= ~(data[keys.present_key("image")] | data[keys.present_key("force")])
    return TensorDict(data, batch_size=[batch_size])


def build(name: str, image_size: int = 64, channels_last: bool = False):
    """The model ``name`` and its training loss, as ``mmf-rl train model=<name>`` builds them for push."""
    cfg = compose_config("train", [f"model={name}"])
    model = build_model(
        to_container(cfg.model), push_modalities(image_size), history=10, horizon=10, target_dim=2
    )
    if channels_last:  # only 4-D tensors (the conv weights) change layout; values stay the same
        model = model.to(memory_format=torch.channels_last)
    return model, build_loss(name, model, LossConfig.from_dict(to_container(cfg.loss)))


def matmul_peak_gflops(n: int = 2048, repeats: int = 20) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    for _ in range(2):
        a @ b
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - start)
    return 2 * n**3 / best / 1e9


def timed(fn, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=10, help="timed training steps")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--profile", action="store_true", help="print the top operators of one training step")
    parser.add_argument("--model", default="forecaster", choices=sorted(MODELS))
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--channels-last", action="store_true", help="conv weights (and so activations) NHWC")
    parser.add_argument("--compile", action="store_true", help="torch.compile the loss module")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    peak_before = matmul_peak_gflops()
    model, loss = build(args.model, args.image_size, args.channels_last)
    if args.compile:
        loss = torch.compile(loss)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    batch = push_like_batch(args.batch_size, image_size=args.image_size)

    def train_step():
        terms = loss(batch)
        total = sum(v for k, v in terms.items() if k.startswith("loss_"))
        optimizer.zero_grad(set_to_none=True)
        total.backward()
        optimizer.step()

    for _ in range(3 if args.compile else 2):
        train_step()
    with FlopCounterMode(display=False) as counter:
        train_step()
    train_flops = counter.get_total_flops()
    step_times = timed(train_step, args.steps)
    step_time = statistics.median(step_times)
    train_gflops = train_flops / step_time / 1e9

    if args.profile:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
            train_step()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))

    model.eval()
    latency = {}
    for b in (1, args.batch_size):
        td = push_like_batch(b, seed=1, image_size=args.image_size)
        with torch.no_grad():
            for _ in range(3):
                model(td.clone())
            latency[b] = statistics.median(timed(lambda td=td: model(td.clone()), 30 if b == 1 else 5))
    # Counted with autograd on (forward only, nothing is backpropagated): FlopCounterMode's module
    # tracker fails on views of parameters made under no_grad.
    with FlopCounterMode(display=False) as counter:
        model(push_like_batch(args.batch_size, seed=1, image_size=args.image_size))
    infer_gflops = counter.get_total_flops() / latency[args.batch_size] / 1e9

    # Other processes on the machine lower a single measurement; the best of two bounds the ceiling.
    peak = max(peak_before, matmul_peak_gflops())
    params = sum(p.numel() for p in model.parameters())
    size = args.image_size
    print(
        f"model: {args.model}, {params / 1e6:.2f} M parameters; batch: image 3x{size}x{size} + force 6 + "
        f"proprio 20, H=10, T=10; {args.threads} threads"
        + "".join(f"; {flag}" for flag in ("channels_last", "compile") if getattr(args, flag))
    )
    print(f"matmul peak (fp32, 2048^3): {peak:.1f} GFLOP/s")
    print(
        f"training  batch {args.batch_size}: {args.batch_size / step_time:.1f} samples/s, "
        f"{step_time * 1e3:.0f} ms/step, {train_flops / 1e9:.1f} GFLOP/step, {train_gflops:.1f} GFLOP/s "
        f"= {train_gflops / peak:.1%} of peak"
    )
    print(f"inference batch 1: {latency[1] * 1e3:.2f} ms")
    print(
        f"inference batch {args.batch_size}: {latency[args.batch_size] * 1e3:.1f} ms "
        f"({args.batch_size / latency[args.batch_size]:.0f} samples/s, {infer_gflops:.1f} GFLOP/s "
        f"= {infer_gflops / peak:.1%} of peak)"
    )


if __name__ == "__main__":
    main()
