"""Training throughput and inference latency of a model (default: the forecaster) on a push-like batch.

    .venv/bin/python benchmarks/model_throughput.py [--batch-size 256] [--steps 10] [--profile]
    .venv/bin/python benchmarks/model_throughput.py --model mult --image-size 32 --batch-size 32
    .venv/bin/python benchmarks/model_throughput.py --channels-last     # a candidate speed-up, same numbers
    .venv/bin/python benchmarks/model_throughput.py --device cuda --precision fp32 bf16 fp16

The batch is what the push benchmark feeds the model: a 64x64 RGB window (``--image-size``),
force (6-D) and proprioception (20-D) sequences, H = 10, T = 10, D = 2, with a mix of presence
patterns. ``--model`` picks any registered model with its ``configs/model/<name>.yaml`` and the
default loss config (what ``benchmarks/accuracy.py`` trains). The achieved GFLOP/s (FLOPs counted
by ``torch.utils.flop_counter`` for one step) is printed as a fraction of a matmul peak measured
in the same run on the same device (and threads), in the precision of the measurement.

``--device`` (cpu, cuda, auto) and ``--precision`` (one or more of fp32, bf16, fp16) train as
``mmf-rl train device=... trainer.precision=...`` does: autocast of the forward, fp32 losses,
loss scaling for fp16 (CUDA only); one training line per precision.

Speed-up candidates, off by default, to compare on a quiet machine against a run without them:
``--channels-last`` stores the ConvNets' weights NHWC, so oneDNN runs the convolutions in that
layout (same forecasts and gradients: tests/benchmarks/synthetic/test_push_like.py); ``--compile`` wraps the
loss module in ``torch.compile`` (the first steps, excluded from the timing, pay the compilation).
The optimizer is the trainer's AdamW (its per-parameter loop); ``--fused-optimizer`` times its fused
kernel instead (``trainer.fused_optimizer=true``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torch.utils.flop_counter import FlopCounterMode

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.synthetic.push_like import build_for_push, push_like_batch
from mmf_rl.devices import resolve_device
from mmf_rl.models import MODELS
from mmf_rl.trainers.trainer import (
    PRECISIONS,
    TrainerConfig,
    check_precision,
    make_optimizer,
    outputs_to_fp32,
)

CANDIDATE_FLAGS = ("channels_last", "compile", "fused_optimizer")  # printed on the model line
COUNTED_OPS = ("copy_", "_to_copy", "transpose", "clone", "mm", "addmm")  # with --profile


def synchronize(device: torch.device | None) -> None:
    if device is not None and device.type == "cuda":
        torch.cuda.synchronize(device)


def matmul_peak_gflops(
    n: int = 2048, repeats: int = 20, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> float:
    a, b = torch.randn(n, n, device=device, dtype=dtype), torch.randn(n, n, device=device, dtype=dtype)
    best = min(timed(lambda: a @ b, repeats + 2, torch.device(device))[2:])
    return 2 * n**3 / best / 1e9


def timed(fn, repeats: int, device: torch.device | None = None) -> list[float]:
    """Wall time of each call, the device's queued work included."""
    times = []
    for _ in range(repeats):
        synchronize(device)
        start = time.perf_counter()
        fn()
        synchronize(device)
        times.append(time.perf_counter() - start)
    return times


def training_step(model, loss, batch: TensorDict, precision: str, device: torch.device, fused: bool):
    """One optimisation step as the trainer takes it in ``precision`` (autocast forward, fp32 losses;
    the trainer's AdamW, ``fused`` or the per-parameter loop)."""
    dtype = PRECISIONS[precision]
    optimizer = make_optimizer(model.parameters(), TrainerConfig(fused_optimizer=fused))
    scaler = torch.amp.GradScaler(device.type, enabled=precision == "fp16")
    if dtype is not None:
        model.register_forward_hook(outputs_to_fp32)

    def step():
        with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
            terms = loss(batch)
        total = sum(v for k, v in terms.items() if k.startswith("loss_"))
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(total).backward()
        scaler.step(optimizer)
        scaler.update()

    return step


def op_counts(prof: torch.profiler.profile) -> str:
    """How many operators the profiled step called: at small batches the CPU step is made of many
    small ops, and unlike their times the counts do not depend on the machine's load."""
    counts = {event.key: event.count for event in prof.key_averages() if event.key.startswith("aten::")}
    named = ", ".join(f"{op} {counts.get(f'aten::{op}', 0)}" for op in COUNTED_OPS)
    return f"op counts of the step: {sum(counts.values())} aten ops; {named}"


def measure_training(args, precision: str, device: torch.device) -> dict[str, float]:
    """Samples/s and achieved GFLOP/s of training in ``precision``, on a freshly built model."""
    torch.manual_seed(0)
    model, loss = build_for_push(args.model, args.image_size, args.channels_last)
    model.to(device)
    if args.compile:
        loss = torch.compile(loss)
    batch = push_like_batch(args.batch_size, image_size=args.image_size).to(device)
    step = training_step(model, loss, batch, precision, device, args.fused_optimizer)
    for _ in range(3 if args.compile else 2):
        step()
    with FlopCounterMode(display=False) as counter:
        step()
    step_time = statistics.median(timed(step, args.steps, device))
    if args.profile:
        with torch.profiler.profile() as prof:
            step()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=20))
        print(op_counts(prof))
    return {
        "step_time": step_time,
        "flops": counter.get_total_flops(),
        "params": sum(p.numel() for p in model.parameters()),
        "model": model,
    }


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=10, help="timed training steps")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--profile", action="store_true", help="print a step's top operators and op counts")
    parser.add_argument("--model", default="forecaster", choices=sorted(MODELS))
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--channels-last", action="store_true", help="conv weights (and so activations) NHWC")
    parser.add_argument("--compile", action="store_true", help="torch.compile the loss module")
    parser.add_argument(
        "--fused-optimizer",
        action="store_true",
        help="AdamW's fused kernel (trainer.fused_optimizer=true), not the per-parameter loop",
    )
    parser.add_argument("--device", default="cpu", help="cpu | cuda[:N] | auto")
    parser.add_argument(
        "--precision", nargs="+", default=["fp32"], choices=list(PRECISIONS), help="one training line each"
    )
    return parser.parse_args()


def measure_inference(model, args, device: torch.device) -> dict[int, float]:
    """Median fp32 forward latency at batch 1 and at the training batch size."""
    model.eval()
    latency = {}
    for b in (1, args.batch_size):
        td = push_like_batch(b, seed=1, image_size=args.image_size).to(device)
        with torch.no_grad():
            for _ in range(3):
                model(td.clone())
            latency[b] = statistics.median(
                timed(lambda td=td: model(td.clone()), 30 if b == 1 else 5, device)
            )
    return latency


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    try:
        for precision in args.precision:
            check_precision(precision, device)
    except ValueError as error:
        raise SystemExit(f"model_throughput.py: error: {error}") from None
    # Inference runs in fp32: that peak is always measured. Other processes on the machine lower a
    # single measurement; the best of two (before and after the model's) bounds the ceiling.
    peak_precisions = ["fp32", *(p for p in args.precision if p != "fp32")]
    peaks = {
        p: matmul_peak_gflops(device=device, dtype=PRECISIONS[p] or torch.float32) for p in peak_precisions
    }
    trained = {p: measure_training(args, p, device) for p in args.precision}
    model = trained[args.precision[0]]["model"]
    latency = measure_inference(model, args, device)
    # Counted with autograd on (forward only, nothing is backpropagated): FlopCounterMode's module
    # tracker fails on views of parameters made under no_grad.
    with FlopCounterMode(display=False) as counter:
        model(push_like_batch(args.batch_size, seed=1, image_size=args.image_size).to(device))
    infer_gflops = counter.get_total_flops() / latency[args.batch_size] / 1e9
    for p in peak_precisions:
        peaks[p] = max(peaks[p], matmul_peak_gflops(device=device, dtype=PRECISIONS[p] or torch.float32))
    size = args.image_size
    print(
        f"model: {args.model}, {trained[args.precision[0]]['params'] / 1e6:.2f} M parameters; batch: image "
        f"3x{size}x{size} + force 6 + proprio 20, H=10, T=10; device {device}"
        + (
            f", {args.threads} threads"
            if device.type == "cpu"
            else f" ({torch.cuda.get_device_name(device)})"
        )
        + "".join(f"; {flag}" for flag in CANDIDATE_FLAGS if getattr(args, flag))
    )
    for p, result in trained.items():
        step_time, gflops = result["step_time"], result["flops"] / result["step_time"] / 1e9
        print(f"matmul peak ({p}, 2048^3): {peaks[p]:.1f} GFLOP/s")
        print(
            f"training  batch {args.batch_size} {p}: {args.batch_size / step_time:.1f} samples/s, "
            f"{step_time * 1e3:.0f} ms/step, {result['flops'] / 1e9:.1f} GFLOP/step, {gflops:.1f} GFLOP/s "
            f"= {gflops / peaks[p]:.1%} of the {p} peak"
        )
    print(f"inference batch 1 (fp32): {latency[1] * 1e3:.2f} ms")
    print(
        f"inference batch {args.batch_size} (fp32): {latency[args.batch_size] * 1e3:.1f} ms "
        f"({args.batch_size / latency[args.batch_size]:.0f} samples/s, {infer_gflops:.1f} GFLOP/s"
        f" = {infer_gflops / peaks['fp32']:.1%} of the fp32 peak)"
    )


if __name__ == "__main__":
    main()
