"""Forecast metrics over a loader: MSE (normalised and in units), ADE/FDE (mean and best-of-K), NLL.

* ``mse``: mean squared error of the forecast mean in the normalised target frame (MultiBench's
  metric for the push task); ``mse_units``: the same in the target's units.
* ``ade`` / ``fde``: average / final Euclidean distance over the target dims, in units, of the
  deterministic forecast (``z = 0``); ``ade_best_of_k`` / ``fde_best_of_k``: of the best of
  ``K`` prior samples per window (chosen by ADE, as is standard).
* ``nll``: Gaussian NLL of the normalised target under the deterministic forecast, per window
  (summed over ``T × D``).
* ``constant_velocity``: the same errors for a constant-velocity extrapolation of the target's
  own past (needs ``"target_past"`` in the batches), a reference every model should beat.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.objectives.common import gaussian_nll


def displacement_errors(forecast: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-window ADE and FDE ``[B]`` for ``[B, T, D]`` forecasts in the target's units."""
    distance = (forecast - target).norm(dim=-1)
    return distance.mean(-1), distance[:, -1]


def constant_velocity(target_past: torch.Tensor, horizon: int) -> torch.Tensor:
    """Extrapolate the last step of ``[B, H, D]`` over ``horizon`` steps."""
    velocity = target_past[:, -1] - target_past[:, -2]
    steps = torch.arange(1, horizon + 1, dtype=target_past.dtype, device=target_past.device)
    return target_past[:, -1:] + velocity[:, None] * steps[None, :, None]


@torch.no_grad()
def evaluate_forecasts(model, batches: Iterable[TensorDictBase], denormalize: Callable[[torch.Tensor], torch.Tensor],
                       num_samples: int = 0, with_baseline: bool = False) -> dict[str, float]:
    """Average the metrics above over every window of ``batches`` (model in eval mode, ``z = 0``).

    ``denormalize`` maps normalised targets to units (``Normalizer.denormalize_target``).
    ``num_samples > 0`` adds the best-of-K errors.
    """
    totals: dict[str, float] = defaultdict(float)
    count = 0
    for batch in batches:
        target = batch.get(keys.TARGET)
        out = model(batch.clone(False))
        loc, scale = out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)
        target_units = denormalize(target)
        forecast_units = denormalize(loc)
        ade, fde = displacement_errors(forecast_units, target_units)
        totals["mse"] += float(((loc - target) ** 2).mean((1, 2)).sum())
        totals["mse_units"] += float(((forecast_units - target_units) ** 2).mean((1, 2)).sum())
        totals["ade"] += float(ade.sum())
        totals["fde"] += float(fde.sum())
        totals["nll"] += float(gaussian_nll(target, loc, scale).flatten(1).sum(-1).sum())
        if num_samples:
            samples = denormalize(model.sample(batch.clone(False), num_samples).get(keys.FORECAST_SAMPLES))
            distance = (samples - target_units[:, None]).norm(dim=-1)  # [B, K, T]
            best = distance.mean(-1).argmin(1)
            rows = torch.arange(len(best))
            totals["ade_best_of_k"] += float(distance.mean(-1)[rows, best].sum())
            totals["fde_best_of_k"] += float(distance[rows, best, -1].sum())
        if with_baseline:
            past = batch.get(keys.TARGET_PAST, None)
            if past is None:
                raise KeyError(f"the constant-velocity baseline needs {keys.TARGET_PAST!r} in the batches "
                               "(data config: include_target_past: true)")
            cv = constant_velocity(past, target.shape[1])
            cv_units = denormalize(cv)
            cv_ade, cv_fde = displacement_errors(cv_units, target_units)
            totals["cv_mse"] += float(((cv - target) ** 2).mean((1, 2)).sum())
            totals["cv_mse_units"] += float(((cv_units - target_units) ** 2).mean((1, 2)).sum())
            totals["cv_ade"] += float(cv_ade.sum())
            totals["cv_fde"] += float(cv_fde.sum())
        count += target.shape[0]
    if count == 0:
        return {}
    return {name: value / count for name, value in totals.items()} | {"windows": float(count)}
