"""A registered model with its training loss, built for the push data's shapes: with
:func:`mmf_rl.datasets.synthetic.push_like_batch`, what measures a model's speed or memory without a
recording (``benchmarks/model_throughput.py``, ``benchmarks/step_cost.py``)."""

from __future__ import annotations

import torch

from mmf_rl.configuration import compose_config, to_container
from mmf_rl.datasets.synthetic import push_modalities
from mmf_rl.models.registry import build_loss, build_model
from mmf_rl.objectives import LossConfig

HISTORY = 10
HORIZON = 10
TARGET_DIM = 2


def build_for_push(name: str, image_size: int = 64, channels_last: bool = False):
    """The model ``name`` and its training loss, as ``mmf-rl train model=<name>`` builds them for
    push. ``channels_last`` stores the convolution weights NHWC (a layout, not a numerical change)."""
    cfg = compose_config("train", [f"model={name}"])
    model = build_model(
        to_container(cfg.model),
        push_modalities(image_size),
        history=HISTORY,
        horizon=HORIZON,
        target_dim=TARGET_DIM,
    )
    if channels_last:  # only 4-D tensors (the conv weights) change layout; values stay the same
        model = model.to(memory_format=torch.channels_last)
    # The loss config group's defaults, which every model gets (the ELBO's KL warm-up too): nothing chosen.
    return model, build_loss(name, model, LossConfig.from_dict(to_container(cfg.loss)), check_unread=False)
