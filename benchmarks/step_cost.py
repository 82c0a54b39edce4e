"""Training-step cost of forecaster variants against MulT, measured side by side in one process.

    .venv/bin/python benchmarks/step_cost.py                  # the standard budget: batch 32, 32x32
    .venv/bin/python benchmarks/step_cost.py --threads 1 --rounds 6

The variants (``VARIANTS``: the default, the paper's raw-token decoder, ``L_mis`` with its teacher
detached, per-frame image tokens), MulT and the recommended preset (MulT with modality dropout and
``L_mis``) train in turn, ``--steps`` steps each per round, on the push-like batch
(``benchmarks.synthetic.push_like.push_like_batch``); the first round warms up and is dropped.
Interleaving the models round by round means a machine that slows down slows every model alike,
so the printed ratios hold where the absolute times do not. Prints each model's median ms per
step and its ratio to MulT's.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.synthetic.push_like import push_like_batch, push_modalities
from mmf_rl.configuration import compose_config, to_container
from mmf_rl.models import build_loss, build_model
from mmf_rl.objectives import LossConfig

# label -> (train overrides, image encoder)
VARIANTS = {
    "forecaster (default)": ((), "conv"),
    "forecaster, raw tokens (the paper)": (("model.decoder_input=tokens",), "conv"),
    "forecaster, L_mis teacher detached": (("loss.detach_teacher=true",), "conv"),
    "forecaster, per-frame image tokens": ((), "conv_frames"),
    "MulT trained for missing sensors (experiment=robust_mult)": (("experiment=robust_mult",), "conv"),
    "MulT": (("model=mult",), "conv"),
}


def build(overrides: tuple[str, ...], image_encoder: str, image_size: int):
    cfg = compose_config("train", list(overrides))
    modalities = push_modalities(image_size)
    modalities[0] = type(modalities[0])("image", "image", modalities[0].shape, encoder=image_encoder)
    torch.manual_seed(0)
    model = build_model(to_container(cfg.model), modalities, history=10, horizon=10, target_dim=2).train()
    # The loss config as composed: its group's defaults unless the variant sets one.
    loss = build_loss(cfg.model.name, model, LossConfig.from_dict(to_container(cfg.loss)), check_unread=False)
    return model, loss, torch.optim.Adam(model.parameters(), lr=1e-3)


def run_steps(model_loss_optimizer, batch, steps: int) -> float:
    _, loss, optimizer = model_loss_optimizer
    start = time.perf_counter()
    for _ in range(steps):
        optimizer.zero_grad()
        sum(v for k, v in loss(batch.clone()).items() if k.startswith("loss_")).backward()
        optimizer.step()
    return (time.perf_counter() - start) / steps * 1e3


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--image-size", type=int, default=32)
    parser.add_argument("--steps", type=int, default=10, help="steps per model per round")
    parser.add_argument("--rounds", type=int, default=6, help="rounds; the first warms up")
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    models = {label: build(*variant, args.image_size) for label, variant in VARIANTS.items()}
    batch = push_like_batch(args.batch_size, image_size=args.image_size)
    times: dict[str, list[float]] = {label: [] for label in models}
    for round_index in range(args.rounds):
        for label, parts in models.items():
            ms = run_steps(parts, batch, args.steps)
            if round_index:
                times[label].append(ms)
    reference = statistics.median(times["MulT"])
    for label, values in times.items():
        ms = statistics.median(values)
        print(f"{label}: {ms:.1f} ms/step, {ms / reference:.2f}x MulT")


if __name__ == "__main__":
    main()
