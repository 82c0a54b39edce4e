"""The torch device a config names (``device=auto|cpu|cuda[:N]``), for every command alike."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """``auto`` picks CUDA when present; a GPU the user asked for never falls back silently to CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(
            f"device={name} was requested but CUDA is not available here; use device=cpu or device=auto"
        )
    return device
