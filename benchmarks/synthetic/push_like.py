"""Random batches shaped like the push data's (`push_like_batch`) and a registered model with its training
loss built for those shapes (`build_for_push`): what measures a model's speed or memory without a
recording (``benchmarks/model_throughput.py``, ``benchmarks/step_cost.py``)."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.configuration import compose_config, to_container
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.registry import build_loss, build_model
from mmf_rl.objectives import LossConfig

HISTORY = 10
HORIZON = 10
TARGET_DIM = 2


def push_modalities(image_size: int = 64) -> list[ModalitySpec]:
    """The push benchmark's modalities: a square RGB image, force (6-D) and proprioception (20-D)."""
    return [
        ModalitySpec("image", "image", (3, image_size, image_size)),
        ModalitySpec("force", "sequence", (6,)),
        ModalitySpec("proprio", "sequence", (20,)),
    ]


def push_like_batch(
    batch_size: int, history: int = 10, horizon: int = 10, seed: int = 0, image_size: int = 64
) -> TensorDict:
    """A random batch shaped like the push benchmark's (``push_modalities``, a 2-D target), mostly
    complete samples and some with one sensor out: the mix the model trains on. For timing a model
    without a recording."""
    g = torch.Generator().manual_seed(seed)
    data = {
        keys.obs_key("image"): torch.randint(
            0, 256, (batch_size, history, 3, image_size, image_size), generator=g, dtype=torch.uint8
        ),
        keys.obs_key("force"): torch.randn(batch_size, history, 6, generator=g),
        keys.obs_key("proprio"): torch.randn(batch_size, history, 20, generator=g),
        keys.TARGET: torch.randn(batch_size, horizon, 2, generator=g),
    }
    for spec in push_modalities(image_size):
        data[spec.present_key] = torch.rand(batch_size, generator=g) > 0.15
    data[keys.present_key("proprio")] |= ~(data[keys.present_key("image")] | data[keys.present_key("force")])
    return TensorDict(data, batch_size=[batch_size])


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
