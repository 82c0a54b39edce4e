"""Turning the ground plane of a window: the values the data config marks as planar rotate together.

A pedestrian turns left as readily as right and walks north as readily as east, but a model
trained on a few scenes learns their dominant directions unless it sees them turned (trajectory
forecasters train with random rotations for this reason). The data config says which dims are the
``(x, y)`` components of a vector in the plane (``planar`` on a vector modality or on the target) and
which cameras are maps of it (``top_down``: world ``x`` to the right, ``y`` up);
``augment.rotation`` turns each training window by its own angle, all of these at once, so every
relation between them (a velocity and the displacement it leads to, a neighbour and the map) holds.
"""

from __future__ import annotations

import torch


def check_pairs(pairs: list[list[int]] | None, width: int, raw: list[int], key: str) -> None:
    """Raise a ValueError naming ``key`` unless ``pairs`` are disjoint ``(x, y)`` index pairs of the
    ``width`` dims, none of them a ``raw_dims`` flag (a flag does not turn)."""
    used: list[int] = []
    for pair in pairs or []:
        if len(pair) != 2 or pair[0] == pair[1]:
            raise ValueError(f"data config: `{key}` entries are [x, y] pairs of two dims, found {pair}")
        if any(not 0 <= i < width for i in pair):
            raise ValueError(
                f"data config: `{key}` pair {pair} must index the {width} dims (after `dims`); fix the "
                "indices"
            )
        if set(pair) & set(used) or set(pair) & set(raw):
            raise ValueError(
                f"data config: `{key}` pair {pair} reuses a dim of another pair or of `raw_dims` {raw}; a "
                "dim is the x or y of one vector"
            )
        used += pair


def rotate_pairs(values: torch.Tensor, pairs: list[list[int]] | None, angles: torch.Tensor) -> torch.Tensor:
    """``values`` ``[B, ..., D]`` with each ``[x, y]`` dim pair turned counter-clockwise by ``angles``
    ``[B]`` (radians, one per sample); the other dims unchanged."""
    if not pairs:
        return values
    xs, ys = [p[0] for p in pairs], [p[1] for p in pairs]
    shape = (-1,) + (1,) * (values.dim() - 1)
    cos, sin = angles.cos().to(values.dtype).view(shape), angles.sin().to(values.dtype).view(shape)
    x, y = values[..., xs], values[..., ys]
    turned = values.clone()
    turned[..., xs] = cos * x - sin * y
    turned[..., ys] = sin * x + cos * y
    return turned


def rotate_frames(frames: torch.Tensor, angles: torch.Tensor) -> torch.Tensor:
    """``uint8 [B, H, C, h, w]`` top-down frames, each sample's ``H`` frames turned about their
    centres by its angle (radians, counter-clockwise as shown: ``x`` right, ``y`` up); what turns in
    from outside the frame is black, as outside a scene's map.

    What torchvision's ``rotate`` does with bilinear interpolation, for a whole batch in one
    ``grid_sample`` call: ``rotate`` takes one angle per call, and a call per sample on the batch
    gatherer's thread holds the interpreter lock long enough to slow the training step beside it.
    """
    b, steps, channels, h, w = frames.shape
    cos, sin, zero = angles.cos().float(), angles.sin().float(), torch.zeros(b)
    # Where each output pixel samples the input, in grid_sample's [-1, 1] coordinates (rows down),
    # scaled by the aspect ratio so that a turn of a non-square frame is a turn in pixels.
    theta = torch.stack(
        [torch.stack([cos, -sin * h / w, zero], -1), torch.stack([sin * w / h, cos, zero], -1)], 1
    )
    images = frames.reshape(b, steps * channels, h, w).float()
    grid = torch.nn.functional.affine_grid(theta, list(images.shape), align_corners=False)
    turned = torch.nn.functional.grid_sample(images, grid, padding_mode="zeros", align_corners=False)
    return turned.round_().clamp_(0, 255).to(torch.uint8).view(b, steps, channels, h, w)
