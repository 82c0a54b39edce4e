"""Run a computation only on the rows of a batch that a mask selects, the others keeping a default.

Modality encoders run on the samples where their modality is present, and the RL glue runs the
forecaster only on the envs with at least one present sensor (the others get the target's
training prior); both are this one gather/compute/scatter.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch


def compute_on_rows(
    mask: torch.Tensor,
    compute: Callable[[torch.Tensor | None], Sequence[torch.Tensor]],
    defaults: Sequence[torch.Tensor],
) -> tuple[torch.Tensor, ...]:
    """``compute`` on the rows where ``mask`` (``[B]`` bool) is True; ``defaults`` (each ``[B, ...]``)
    elsewhere.

    ``compute(rows)`` returns one tensor per default, for the selected rows: ``rows`` is an index
    tensor, or ``None`` when every row is selected, so the caller passes its inputs whole (no gather
    copy: an image window batch is tens of MB) and its results are returned as they are. Nothing is
    computed when no row is selected. The scatter is out of place, so gradients reach ``compute``.
    """
    if bool(mask.all()):
        return tuple(compute(None))
    if not bool(mask.any()):
        return tuple(defaults)
    rows = mask.nonzero().squeeze(1)
    values = compute(rows)
    return tuple(
        default.index_copy(0, rows.to(default.device), value.to(default.device))
        for default, value in zip(defaults, values, strict=True)
    )
