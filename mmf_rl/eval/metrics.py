"""Forecast metrics over a loader, per window and per presence subset (paired).

Per window, then averaged over windows:

* ``mse``: mean squared error of the point forecast (the forecast mean; for a latent model the
  forecast of its ``eval_latent``, by default the decode of the prior's mean) in the normalised
  target frame (MultiBench's metric for the push task); ``mse_units``: the same in the target's
  units.
* ``ade`` / ``fde``: average / final Euclidean distance over the target dims, in units, of the
  point forecast.
* ``min_mse_k``, ``min_ade_k``, ``min_fde_k`` (with ``num_samples = K > 0``): the smallest MSE
  (normalised), ADE and FDE (units) over ``K`` forecasts decoded from prior samples, each minimum
  taken independently (the sample with the best ADE need not have the best FDE).
* ``nll``: NLL of the normalised target under the point forecast's distribution (summed over
  ``T × D``): the output family at the forecast's scale, with a level curve too (the family at the
  pattern's 90% scale; the curve changes the intervals, not the density the NLL reads).
* ``coverage_50`` / ``coverage_90``: share of the ``T × D`` target values inside the central
  50% / 90% interval of the forecast's distribution: a calibrated scale gives 0.5 / 0.9.
* ``width_90``: mean width of those central 90% intervals, in the target's units: of two forecasts
  that cover as well, the narrower says more (an interval can cover by being uselessly wide).
* ``crps``: the continuous ranked probability score of the forecast's distribution, in the normalised
  target frame, averaged over the ``T × D`` values: a proper score, rewarding calibration and
  sharpness at once (lower is better; for a point forecast it is the absolute error).
* ``kl`` (latent models): ``KL(q(z | X[, y]) || p(z | X))`` in nats, summed over ``d_z``: what the
  latent carries beyond the prior; near zero, the latent has collapsed and the forecast does not
  depend on it.
* ``cv_*`` (``with_baseline``): the errors of a constant-velocity extrapolation of the target's
  own past (needs ``"target_past"``), a reference every model should beat.

The forecast's distribution is the model's output family (its config's ``output_distribution``,
:func:`~mmf_rl.objectives.output_distribution_of`): ``N(loc, scale²)`` by default, or a Laplace or
Student-t with that location and scale; the NLL, the intervals and the CRPS are its. A model
calibrated with a level curve (``mmf-rl calibrate method=levels``,
:mod:`mmf_rl.models.scale_calibration`) has the intervals of its window's presence pattern's curve
instead: ``coverage_50``, ``coverage_90`` and ``width_90`` read the curve's half widths, and ``crps``
is the CRPS of the recalibrated quantile function, the integral of the quantile (pinball) score over
the levels, ``2 ∫ ρ_τ(y - Q(τ)) dτ``, by the midpoint rule on :data:`CRPS_QUANTILES` levels
(within 0.05% of the closed form per value under the family's own curve, where the closed form is used).

:func:`evaluate_presence_subsets` scores the named presence subsets **paired**: every subset row
is averaged over the same windows, those in which each compared subset keeps a present modality.
On data where some windows already lack a modality, unpaired rows would each average a
different window set, and a subset that removes a sensor could even look better than all of them.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.datasets.protocols import apply_presence_subset
from mmf_rl.models.baselines.constant_velocity import constant_velocity
from mmf_rl.models.scale_calibration import level_half_widths
from mmf_rl.objectives.common import gaussian_kl
from mmf_rl.objectives.distributions import OutputDistribution, output_distribution, output_distribution_of

COVERAGE_LEVELS = {"coverage_50": 0.5, "coverage_90": 0.9}
# The quantile levels of the CRPS under a level curve, by the midpoint rule: within 0.05% of the
# closed forms of the Gaussian, Laplace and Student-t (df 2.5) at 400.
CRPS_QUANTILES = 400
BASELINE_PREFIX = "cv_"


def displacement_errors(forecast: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-window average and final displacement errors (Euclidean over the target's dims).

    Args:
        forecast (torch.Tensor): ``[B, T, D]`` forecasts, in the target's units.
        target (torch.Tensor): ``[B, T, D]`` targets, in the same units.

    Returns:
        ``(ade, fde)``, each ``[B]``.

    Examples:
        >>> import torch
        >>> from mmf_rl.eval import displacement_errors
        >>> target = torch.zeros(1, 2, 2)
        >>> displacement_errors(torch.tensor([[[3.0, 4.0], [0.0, 1.0]]]), target)
        (tensor([3.]), tensor([1.]))
    """
    distance = (forecast - target).norm(dim=-1)
    return distance.mean(-1), distance[:, -1]


def point_errors(
    forecast: torch.Tensor, target: torch.Tensor, forecast_units: torch.Tensor, target_units: torch.Tensor
) -> dict[str, torch.Tensor]:
    """``mse`` (normalised), ``mse_units``, ``ade``, ``fde`` ``[B]`` of ``[B, T, D]`` point forecasts,
    given normalised and in units."""
    ade, fde = displacement_errors(forecast_units, target_units)
    return {
        "mse": ((forecast - target) ** 2).mean((1, 2)),
        "mse_units": ((forecast_units - target_units) ** 2).mean((1, 2)),
        "ade": ade,
        "fde": fde,
    }


NORMAL = output_distribution("normal")


def central_half_width(level: float, family: OutputDistribution = NORMAL) -> float:
    """The half width of the central ``level`` interval of the standard member of ``family`` (by
    default ``N(0, 1)``)."""
    return family.half_width(level)


def _half_width(level: float, family: OutputDistribution, curve: torch.Tensor | None, dims: int):
    """The central ``level`` half width in units of scale: the family's (a float), or per window
    under the level curves ``curve`` ``[B, len(LEVELS)]``, shaped ``[B, 1, ...]`` for ``dims``-dim values."""
    if curve is None:
        return family.half_width(level)
    return level_half_widths(curve, [level], family).view(-1, *[1] * (dims - 1))


def interval_coverage(
    target: torch.Tensor,
    loc: torch.Tensor,
    scale: torch.Tensor,
    level: float,
    family: OutputDistribution = NORMAL,
    curve: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per window ``[B]``: the share of ``target`` values inside the central ``level`` interval of the
    ``family`` member at ``(loc, scale)`` (``[B, T, D]`` each; by default ``N(loc, scale²)``):
    ``|target - loc| <= half_width(level) · scale``; with ``curve``, each window's level curve
    ``[B, len(LEVELS)]``, its half width (:func:`~mmf_rl.models.scale_calibration.level_half_widths`)."""
    half = _half_width(level, family, curve, target.dim())
    return ((target - loc).abs() <= half * scale).flatten(1).float().mean(-1)


def interval_width(
    loc: torch.Tensor,
    scale: torch.Tensor,
    level: float,
    denormalize: Callable[[torch.Tensor], torch.Tensor],
    family: OutputDistribution = NORMAL,
    curve: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per window ``[B]``: the mean width in units of the central ``level`` intervals of the ``family``
    members at ``(loc, scale)`` (``[B, T, D]`` each, normalised; by default ``N(loc, scale²)``; with
    ``curve``, each window's level curve's intervals)."""
    half = _half_width(level, family, curve, loc.dim()) * scale
    return (denormalize(loc + half) - denormalize(loc - half)).flatten(1).mean(-1)


def forecast_crps(
    target: torch.Tensor,
    loc: torch.Tensor,
    scale: torch.Tensor,
    family: OutputDistribution = NORMAL,
    curve: torch.Tensor | None = None,
) -> torch.Tensor:
    """Per window ``[B]``: the mean over ``T × D`` values of the CRPS of the ``family`` member at
    ``(loc, scale)`` at ``target``, in the family's closed form (:meth:`OutputDistribution.crps`); with
    ``curve`` (each window's level curve ``[B, len(LEVELS)]``), of its recalibrated quantile function
    (:func:`quantile_crps`) where a window's curve is not the family's own (all ones)."""
    closed = family.crps(target, loc, scale).flatten(1).mean(-1)
    if curve is None:
        return closed
    own = (curve == 1).all(-1)
    if bool(own.all()):
        return closed
    return torch.where(own, closed, quantile_crps(target, loc, scale, curve, family).flatten(1).mean(-1))


def gaussian_crps(target: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Per window ``[B]``: the mean over ``T × D`` values of the CRPS of ``N(loc, scale²)`` at
    ``target``, in closed form (Gneiting & Raftery 2007),
    ``scale · (z (2 Φ(z) - 1) + 2 φ(z) - 1 / sqrt(pi))`` with ``z = (target - loc) / scale``; one
    line, so no scoring library (properscoring, scoringrules) is needed."""
    return forecast_crps(target, loc, scale, NORMAL)


def quantile_crps(
    target: torch.Tensor,
    loc: torch.Tensor,
    scale: torch.Tensor,
    curve: torch.Tensor,
    family: OutputDistribution,
    quantiles: int = CRPS_QUANTILES,
) -> torch.Tensor:
    """Elementwise CRPS ``[B, T, ...]`` of the forecast whose quantile at level ``τ`` is ``loc + scale ·
    sign(τ - 1/2) · h(|2τ - 1|)``, ``h`` the half widths of each window's level curve ``curve`` ``[B,
    len(LEVELS)]`` (:func:`~mmf_rl.models.scale_calibration.level_half_widths`): ``2 ∫ ρ_τ(y - Q(τ)) dτ``
    over ``(0, 1)``, ``ρ_τ(u) = u (τ - 1{u < 0})`` the pinball loss, by the midpoint rule on
    ``quantiles`` levels (an even number; symmetric pairs ``τ``, ``1 - τ`` share a half width).
    Under ones (the family's own curve) it is the family's CRPS within the rule's error.

    The sum over the levels is exact in closed form: ``ρ_τ(y - h) + ρ_{1-τ}(y + h)`` is ``y + h (1 - 2τ)``
    less ``y - h`` where ``h > y`` and less ``y + h`` where ``h < -y``; the half widths are nondecreasing
    in ``τ``, so those levels are a suffix and a prefix of the pairs, found by a binary search, whose sums
    come from the running sums of the half widths (no ``values × levels`` table)."""
    if quantiles < 2 or quantiles % 2:
        raise ValueError(f"quantiles must be an even number >= 2, found {quantiles}")
    pairs = quantiles // 2
    upper = 0.5 + (torch.arange(pairs, dtype=torch.float64) + 0.5) / quantiles  # tau in (1/2, 1)
    half = level_half_widths(curve.double(), (2 * upper - 1).tolist(), family)  # [B, pairs]
    z = ((target - loc) / scale).double()
    flat = z.reshape(z.shape[0], -1)  # [B, V]
    half = half.to(z.device).expand(flat.shape[0], pairs).contiguous()
    upper = upper.to(z.device)
    running = torch.nn.functional.pad(half.cumsum(-1), (1, 0))  # [B, pairs + 1]: sum of h_j, j < i
    above = torch.searchsorted(half, flat, right=True)  # first pair with h > y
    below = torch.searchsorted(half, -flat)  # first pair with h >= -y
    total = pairs * flat + (half * (1 - 2 * upper)).sum(-1, keepdim=True)
    total -= (pairs - above) * flat - (running[:, -1:] - running.gather(1, above))
    total -= below * flat + running.gather(1, below)
    return (2 * total / quantiles).view_as(z).to(target.dtype) * scale


def best_of_samples(
    samples: torch.Tensor, target: torch.Tensor, samples_units: torch.Tensor, target_units: torch.Tensor
) -> dict[str, torch.Tensor]:
    """``min_mse_k`` (normalised), ``min_ade_k``, ``min_fde_k`` (units) ``[B]`` of ``[B, K, T, D]``
    samples against ``[B, T, D]`` targets, each the minimum over ``K`` on its own."""
    mse = ((samples - target[:, None]) ** 2).mean((2, 3))
    distance = (samples_units - target_units[:, None]).norm(dim=-1)  # [B, K, T]
    return {
        "min_mse_k": mse.amin(1),
        "min_ade_k": distance.mean(-1).amin(1),
        "min_fde_k": distance[..., -1].amin(1),
    }


def window_metrics(
    model,
    batch: TensorDictBase,
    denormalize: Callable[[torch.Tensor], torch.Tensor],
    num_samples: int = 0,
    with_baseline: bool = False,
) -> dict[str, torch.Tensor]:
    """Every metric above for each window of ``batch`` (model in eval mode): ``{name: [B]}``."""
    target = batch.get(keys.TARGET)
    # The model sees no target: a point forecast must not depend on the future it forecasts.
    inputs = batch.exclude(keys.TARGET)
    out = model(inputs.clone(False))
    loc, scale = out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)
    family = output_distribution_of(model)
    curve = level_curves(model, out)
    target_units = denormalize(target)
    metrics = point_errors(loc, target, denormalize(loc), target_units)
    # The family at the forecast's scale (a pattern's 90% scale when calibrated), curve or not.
    metrics["nll"] = family.nll(target, loc, scale).flatten(1).sum(-1)
    metrics |= {
        name: interval_coverage(target, loc, scale, level, family, curve)
        for name, level in COVERAGE_LEVELS.items()
    }
    metrics["width_90"] = interval_width(
        loc, scale, COVERAGE_LEVELS["coverage_90"], denormalize, family, curve
    )
    metrics["crps"] = forecast_crps(target, loc, scale, family, curve)
    kl = latent_kl(model, batch, out)
    if kl is not None:
        metrics["kl"] = kl
    if num_samples:
        samples = model.sample(inputs.clone(False), num_samples).get(keys.FORECAST_SAMPLES)
        metrics |= best_of_samples(samples, target, denormalize(samples), target_units)
    if with_baseline:
        metrics |= baseline_metrics(batch, denormalize)
    return {name: value.detach().float().cpu() for name, value in metrics.items()}


def level_curves(model, out: TensorDictBase) -> torch.Tensor | None:
    """``[B, len(LEVELS)]``: the level curve of each window's presence pattern (the presence the model
    used, in its output), or ``None`` when the model has none but the family's (uncalibrated, a
    ``coverage`` or ``temperature`` fit, a model without ``scale_calibration``)."""
    calibration = getattr(model, "scale_calibration", None)
    if calibration is None or not calibration.has_level_curve():
        return None
    present = torch.stack([out.get(keys.present_key(spec.name)) for spec in model.modalities], dim=1)
    return calibration.level_curve(present.to(calibration.level_factors.device))


def latent_kl(model, batch: TensorDictBase, out: TensorDictBase) -> torch.Tensor | None:
    """``[B]`` KL of the posterior to the prior in nats, or ``None`` for a model without a latent.

    ``out`` is the model's output without the target; a posterior that reads the target is
    computed by a second pass with it (the forecast itself never sees the target)."""
    if keys.PRIOR_LOC not in out.keys(include_nested=True):
        return None
    if keys.POSTERIOR_LOC not in out.keys(include_nested=True):
        out = model(batch.clone(False))
    return gaussian_kl(
        out.get(keys.POSTERIOR_LOC),
        out.get(keys.POSTERIOR_SCALE),
        out.get(keys.PRIOR_LOC),
        out.get(keys.PRIOR_SCALE),
    ).sum(-1)


def baseline_metrics(
    batch: TensorDictBase, denormalize: Callable[[torch.Tensor], torch.Tensor]
) -> dict[str, torch.Tensor]:
    """The constant-velocity reference's ``cv_mse``, ``cv_mse_units``, ``cv_ade``, ``cv_fde`` ``[B]``."""
    past = batch.get(keys.TARGET_PAST, None)
    if past is None:
        raise KeyError(
            f"the constant-velocity baseline needs {keys.TARGET_PAST!r} in the batches "
            "(data config: include_target_past: true)"
        )
    target = batch.get(keys.TARGET)
    cv = constant_velocity(past, target.shape[1])
    errors = point_errors(cv, target, denormalize(cv), denormalize(target))
    return {f"{BASELINE_PREFIX}{name}": value for name, value in errors.items()}


@torch.no_grad()
def evaluate_forecasts(
    model,
    batches: Iterable[TensorDictBase],
    denormalize: Callable[[torch.Tensor], torch.Tensor],
    num_samples: int = 0,
    with_baseline: bool = False,
) -> dict[str, float]:
    """Average the metrics above over every window of ``batches`` (model in eval mode).

    Args:
        model (nn.Module): a model following `mmf_rl.keys`; it never sees the target of a window.
        batches (Iterable[TensorDictBase]): batches with ``"target"`` (e.g. a ``"test"`` loader).
        denormalize (Callable[[torch.Tensor], torch.Tensor]): maps normalised targets to units
            (``Normalizer.denormalize_target``).
        num_samples (int, optional): ``K > 0`` adds the best-of-K errors (``model.sample``). Defaults
            to ``0``.
        with_baseline (bool, optional): add the constant-velocity reference's ``cv_*`` errors (needs
            ``"target_past"``). Defaults to ``False``.

    Returns:
        ``{metric: mean over windows}`` (see the module docstring) plus ``windows``, their count;
        ``{}`` when there is no window.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.eval import evaluate_forecasts
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,))],
        ...     history=4, horizon=5, d_model=16, d_latent=4, num_heads=2,
        ... )).eval()
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2), "target_past": torch.randn(8, 4, 2),
        ... }, batch_size=[8])
        >>> metrics = evaluate_forecasts(model, [batch], lambda t: t * 0.1, num_samples=4, with_baseline=True)
        >>> sorted(metrics)
        ['ade', 'coverage_50', 'coverage_90', 'crps', 'cv_ade', 'cv_fde', 'cv_mse', 'cv_mse_units', 'fde',
         'kl', 'min_ade_k', 'min_fde_k', 'min_mse_k', 'mse', 'mse_units', 'nll', 'width_90', 'windows']
        >>> metrics["windows"]
        8.0
    """
    totals: dict[str, float] = defaultdict(float)
    count = 0
    for batch in batches:
        for name, values in window_metrics(model, batch, denormalize, num_samples, with_baseline).items():
            totals[name] += float(values.sum())
        count += batch.shape[0]
    if count == 0:
        return {}
    return {name: value / count for name, value in totals.items()} | {"windows": float(count)}


def scorable_windows(batch: TensorDictBase, subset: Mapping[str, bool]) -> torch.Tensor:
    """``[B]`` bool: the windows that keep at least one present modality under ``subset``."""
    rows = torch.zeros(batch.shape[0], dtype=torch.bool)
    for name, kept in subset.items():
        if kept:
            rows |= batch.get(keys.present_key(name)).cpu()
    return rows


@torch.no_grad()
def evaluate_presence_subsets(
    model,
    batches: Iterable[TensorDictBase],
    subsets: Iterable[tuple[str, Mapping[str, bool]]],
    denormalize: Callable[[torch.Tensor], torch.Tensor],
    num_samples: int = 0,
    with_baseline: bool = False,
    device: torch.device | str = "cpu",
) -> tuple[dict[str, dict[str, float]], dict[str, float] | None]:
    """Score each named presence subset on the **same** windows, in one pass over ``batches``.

    A window belongs to a subset's row when the subset keeps one of its present modalities
    (:func:`~mmf_rl.datasets.protocols.apply_presence_subset`). Subsets with no such window at
    all are left out (e.g. ``only_camera`` on data without camera); every other row is averaged
    over the windows that all of them share. Each row reports ``windows`` (the shared windows it
    is averaged over), ``windows_available`` (the windows it could be scored on alone) and, when
    ``"all"`` is a row, ``degradation`` (its MSE relative to ``"all"``, on the same windows).

    ``batches`` are on the CPU; each subset's batch is moved to ``device``. Returns the rows and
    the constant-velocity reference on the shared windows (``with_baseline``; else ``None``).
    Raises ``ValueError`` if the scored subsets share no window.
    """
    subsets = list(subsets)
    masks, scored, baseline = _score_subsets(
        model, batches, subsets, denormalize, num_samples, with_baseline, device
    )
    available = {name: torch.cat(m) if m else torch.zeros(0, dtype=torch.bool) for name, m in masks.items()}
    scored_names = [name for name, _ in subsets if available[name].any()]
    if not scored_names:
        return {}, None
    shared = torch.stack([available[name] for name in scored_names]).all(0)
    if not shared.any():
        counts = {name: int(available[name].sum()) for name in scored_names}
        raise ValueError(
            f"no window can be scored in every presence subset (windows per subset: {counts}): a "
            "paired comparison needs windows where each subset keeps a present modality"
        )
    results = {name: _shared_row(scored[name], available[name], shared) for name in scored_names}
    if "all" in results:
        reference_mse = results["all"]["mse"]
        for row in results.values():
            row["degradation"] = row["mse"] / reference_mse - 1 if reference_mse > 0 else float("nan")
    reference = None
    if with_baseline:
        reference = {
            metric.removeprefix(BASELINE_PREFIX): float(torch.cat(parts)[shared].mean())
            for metric, parts in baseline.items()
        } | {"windows": float(shared.sum())}
    return results, reference


def _score_subsets(model, batches, subsets, denormalize, num_samples, with_baseline, device):
    """One pass over ``batches``: per subset, the scorable-window masks and the per-window metrics
    of each batch (``{}`` where it has no scorable window), and the constant-velocity reference's."""
    masks: dict[str, list[torch.Tensor]] = {name: [] for name, _ in subsets}
    scored: dict[str, list[dict[str, torch.Tensor]]] = {name: [] for name, _ in subsets}
    baseline: dict[str, list[torch.Tensor]] = defaultdict(list)
    for batch in batches:
        if batch.shape[0] == 0:
            continue
        for name, subset in subsets:
            rows = scorable_windows(batch, subset)
            masks[name].append(rows)
            scored[name].append(
                window_metrics(
                    model, apply_presence_subset(batch, subset).to(device), denormalize, num_samples
                )
                if rows.any()
                else {}
            )
        if with_baseline:
            for metric, per_window in baseline_metrics(batch, denormalize).items():
                baseline[metric].append(per_window.detach().float().cpu())
    return masks, scored, baseline


def _shared_row(parts: list[dict[str, torch.Tensor]], available: torch.Tensor, shared: torch.Tensor) -> dict:
    """A subset's row: each metric averaged over the ``shared`` windows, and the window counts."""
    metrics = next(part for part in parts if part).keys()
    row = {}
    for metric in metrics:
        # Back to one value per window of the pass (NaN where the subset has no present modality).
        per_window = torch.full((len(shared),), float("nan"))
        per_window[available] = torch.cat([part[metric] for part in parts if part])
        row[metric] = float(per_window[shared].mean())
    return row | {"windows": float(shared.sum()), "windows_available": float(available.sum())}
