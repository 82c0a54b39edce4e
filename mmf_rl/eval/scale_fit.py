"""Fit a trained model's per-presence-pattern scale factors on held-out windows, and store them.

The factors (:class:`~mmf_rl.models.scale_calibration.PresenceScaleCalibration`) are fitted in closed
form, for each presence pattern ``p``, on the standardised errors ``z = (y - loc) / scale`` of the
T × D future values of the windows with pattern ``p``, by one of three methods:

* ``coverage``: split-conformal. ``s_p`` is the ``⌈(n + 1) · 0.9⌉``-th smallest of the
  ``n`` values ``|z|`` (halfway to the next one), divided by the half width of the central 90%
  interval of the output family's standard member (``N(0, 1)`` by default): the scaled 90% intervals
  then hold that share of the fitted values, each value counted as ``coverage_90`` counts them
  (:mod:`mmf_rl.eval.metrics`); a factor of 1 means the forecast was calibrated at 90% under its
  family. ``n`` counts values, not windows: a window's values are not independent, so the
  finite-sample correction is approximate, and negligible from a few windows on.
  A few large errors (contact, a camera glitch) move a quantile by a few values only.
* ``levels`` (the default): the ``coverage`` factor, and a level curve per pattern
  (:mod:`mmf_rl.models.scale_calibration`): at each central level ``L_k`` of
  :data:`~mmf_rl.models.scale_calibration.LEVELS` (10% to 90% by tenths, 95%, 99%) the same
  finite-sample-corrected quantile of the values ``|z| / s_p``, at rank ``⌈(n + 1) · L_k⌉``, divided
  by the family's ``L_k`` half width (the coverage factor generalised to a level), their half widths
  made nondecreasing by a running maximum. The factor still holds 90% (the curve is 1 there), so
  whatever reads one scale (the NLL, the world model, the transforms) is the family at the pattern's
  90% scale; the intervals at any level, and the CRPS, read the curve (``eval``,
  :mod:`mmf_rl.eval.metrics`). On errors more peaked or heavier-tailed than the family, where one
  factor fitted at 90% over-covers the 50% intervals, the curve holds both.
* ``temperature``: the NLL-optimal scalar temperature of the forecast under its output family:
  ``s_p² = mean(z²)`` for the Gaussian, ``s_p = mean(|z|)`` for the Laplace, a 1-D minimisation of the
  mean NLL for the Student-t (no closed form; :meth:`~mmf_rl.objectives.OutputDistribution.temperature`).
  Under the Gaussian, large errors dominate the mean: on heavy-tailed errors it widens every
  interval to fit the outliers, and the intervals over-cover.

The output family is the model's (its config's ``output_distribution``,
:func:`~mmf_rl.objectives.output_distribution_of`): on errors heavier-tailed than a Gaussian, one
Gaussian factor fitted at 90% over-covers the 50% intervals, a heavier-tailed family can hold both.

The errors are taken on every window of the batches under every presence subset of the evaluation
(:func:`~mmf_rl.datasets.presence_subsets`, applied as :func:`~mmf_rl.datasets.apply_presence_subset`
does), each (window, pattern) pair once. The fit starts from the uncalibrated scale (the factors
are reset to ones first), so refitting replaces earlier factors. A pattern seen in fewer than
``min_windows`` windows gets the pooled fit, the same method on every (window, pattern) pair (its
factor and, by ``levels``, its curve), as a fit from a handful of windows would be noise; when even
those are fewer, it keeps the factor 1 and the family's own curve.
Fit on the validation split (``mmf-rl calibrate`` does): the test split must stay unseen.

``per_step=True`` also fits each horizon step ``t`` of a pattern on its own (the same method on the
values of step ``t`` alone), stored as the step factors relative to the pattern's factor, so that
errors growing with the horizon faster than the scale does are matched at every step, where the
pattern's one factor widens the early steps' intervals and narrows the late ones'. A window holds
every step, so a pattern's steps have its window count and the same ``min_windows`` applies: a
pattern with fewer windows falls back to its pooled factor at every step. A step's fit rests on
``1 / T`` of the pattern's values (still one per window and target dimension), so its quantile is
noisier: off by default. With ``levels`` the curve stays one per pattern, fitted on the values
``|z|`` divided by their step's factor (the pattern's factor times its step's), so it describes the
errors' shape once the step factors have matched their growth.

:func:`save_calibration` writes the factors where the model was loaded from (a checkpoint is
re-saved at its step, a ``save_pretrained`` directory rewritten) and into its twin, the run's
``model/`` export or last checkpoint, when that holds the same weights; each write is atomic.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from safetensors.torch import load_file
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.checkpoint import (
    MODEL_FILE,
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
)
from mmf_rl.datasets import apply_presence_subset, presence_subsets
from mmf_rl.eval.metrics import COVERAGE_LEVELS, central_half_width
from mmf_rl.models import TrainedModelSource
from mmf_rl.models.loading import RUN_EXPORT_DIR
from mmf_rl.models.scale_calibration import LEVELS, level_half_widths, pattern_name
from mmf_rl.objectives.distributions import OutputDistribution, output_distribution, output_distribution_of

DEFAULT_MIN_WINDOWS = 32
# The factors' names in a registered model's state dict.
FACTORS_KEY = "scale_calibration.factors"
STEP_FACTORS_KEY = "scale_calibration.step_factors"
LEVEL_FACTORS_KEY = "scale_calibration.level_factors"
CALIBRATION_KEYS = (FACTORS_KEY, STEP_FACTORS_KEY, LEVEL_FACTORS_KEY)
# The level the coverage fit holds, and the coverage the fit reports: the 90% the README promises.
LEVEL_90 = COVERAGE_LEVELS["coverage_90"]
LEVEL_50 = COVERAGE_LEVELS["coverage_50"]
HALF_WIDTH_90 = central_half_width(LEVEL_90)  # the Gaussian's; a family's is family.half_width(LEVEL_90)
NORMAL = output_distribution("normal")


def conformal_quantiles(magnitudes: torch.Tensor, levels: Sequence[float]) -> torch.Tensor:
    """``[len(levels)]`` float64: the split-conformal quantile of the values ``|z|`` at each level: the
    ``⌈(n + 1) · level⌉``-th smallest of the ``n`` values (the largest when there are too few), halfway
    to the next one."""
    ordered = magnitudes.flatten().double().sort().values
    n = len(ordered)
    quantiles = []
    for level in levels:
        # Fewer than 1 / (1 - level) - 1 values: the corrected rank is past the largest; take that.
        # (The tolerance: (n + 1) * level is a whole number in exact arithmetic more often than in
        # floating point, e.g. 1000 * 0.3.)
        rank = min(math.ceil((n + 1) * level - 1e-9), n)
        # Any factor from the rank-th value up to the next covers the same fitted values; halfway,
        # float32 rounding in the calibrated forecast cannot move the rank-th one out of its interval.
        quantiles.append((ordered[rank - 1] + ordered[min(rank, n - 1)]) / 2)
    return torch.stack(quantiles)


def coverage_factor(
    magnitudes: torch.Tensor, family: OutputDistribution = NORMAL, level: float = LEVEL_90
) -> float:
    """The split-conformal factor of the values ``|z|`` under the output ``family`` (see module
    docstring; by default the Gaussian) at the central ``level`` (by default 90%).

    A hand-written quantile, not MAPIE, crepes or torchcp: they wrap a regressor and compute its
    conformity scores themselves, where the scores here are the model's standardised errors, and
    the fit is this one order statistic."""
    return float(conformal_quantiles(magnitudes, [level])[0]) / family.half_width(level)


def level_curve(magnitudes: torch.Tensor, family: OutputDistribution = NORMAL) -> torch.Tensor:
    """``[len(LEVELS)]`` float64: the level curve of the values ``|z|`` (already divided by their
    scale factor) under ``family``: at each level of :data:`~mmf_rl.models.scale_calibration.LEVELS`,
    the split-conformal quantile (:func:`conformal_quantiles`), made nondecreasing over the levels by
    a running maximum, divided by the family's half width there (see module docstring)."""
    heights = conformal_quantiles(magnitudes, LEVELS).cummax(0).values
    return heights / torch.tensor([family.half_width(level) for level in LEVELS], dtype=torch.float64)


def temperature_factor(magnitudes: torch.Tensor, family: OutputDistribution = NORMAL) -> float:
    """The NLL-optimal temperature of the values ``|z|`` under the output ``family``: ``sqrt(mean(z²))``
    for the Gaussian (the default), ``mean(|z|)`` for the Laplace, a 1-D minimisation of the NLL for a
    family without a closed form (:meth:`~mmf_rl.objectives.OutputDistribution.temperature`)."""
    return family.temperature(magnitudes)


# Each method's scale factor; the methods of LEVEL_CURVE_METHODS also fit each pattern's level curve.
CALIBRATION_METHODS = {
    "coverage": coverage_factor,
    "levels": coverage_factor,
    "temperature": temperature_factor,
}
LEVEL_CURVE_METHODS = ("levels",)
DEFAULT_METHOD = "levels"


@dataclass(frozen=True)
class PatternFit:
    """One presence pattern's fit: its windows, factor, and 50% and 90% coverage before and after on
    the fitted windows (after: under the level curve when the method fits one). ``fitted=False``: fewer
    than ``min_windows`` windows, the factor (and curve) is the pooled fit's (``pooled=True``) or 1
    (also in records written before the pooled fit existed). ``step_factors``: with ``per_step``, the
    factor of each horizon step (the pattern's factor times its step's); ``None`` when the pattern has
    one factor for every step. ``level_factors``: by ``levels``, the pattern's level curve (one entry a
    level of :data:`~mmf_rl.models.scale_calibration.LEVELS`); ``None`` for the family's own.
    ``coverage_50_*``: ``None`` in records written before they were reported."""

    pattern: str
    index: int
    windows: int
    factor: float
    fitted: bool
    coverage_90_before: float
    coverage_90_after: float
    pooled: bool = False
    step_factors: list[float] | None = None
    coverage_50_before: float | None = None
    coverage_50_after: float | None = None
    level_factors: list[float] | None = None


def _calibration_module(model):
    calibration = getattr(model, "scale_calibration", None)
    if calibration is None:
        raise TypeError(
            f"{type(model).__name__} has no per-presence-pattern scale factors (scale_calibration); "
            "only the registered models (mmf_rl.models.MODELS) can be calibrated"
        )
    return calibration


def _presence(batch: TensorDictBase, names: list[str], where: str) -> torch.Tensor:
    """``[B, M]`` bool ``("present", m)`` of ``batch``; a missing key is a clear error."""
    found = batch.keys(include_nested=True)
    absent = [keys.present_key(n) for n in names if keys.present_key(n) not in found]
    if absent:
        raise KeyError(
            f"{where} lacks the presence flags {absent}: the scale factors are per presence pattern, and "
            "every batch needs ('present', m) for each of the model's modalities (mmf_rl.keys)"
        )
    return torch.stack([batch.get(keys.present_key(n)).cpu() for n in names], dim=1)


@dataclass
class StandardisedErrors:
    """A model's standardised errors ``|z|`` under its scale as trained, per presence pattern (the
    index of :class:`~mmf_rl.models.scale_calibration.PresenceScaleCalibration`): ``windows`` counts
    each pattern's windows, ``magnitudes`` holds its values ``[windows, T, ...]``; ``names``: the
    modalities the pattern indices are over."""

    names: list[str]
    windows: dict[int, int]
    magnitudes: dict[int, torch.Tensor]

    def pooled(self, other: StandardisedErrors) -> StandardisedErrors:
        """These errors and ``other``'s together, pattern by pattern (the same modalities, the same
        horizon and target size)."""
        if other.names != self.names:
            raise ValueError(
                f"errors over modalities {other.names} cannot be pooled with errors over {self.names}: "
                "the presence patterns would not mean the same"
            )
        patterns = sorted(self.windows.keys() | other.windows.keys())
        magnitudes = {}
        for index in patterns:
            parts = [e.magnitudes[index] for e in (self, other) if index in e.magnitudes]
            if len({part.shape[1:] for part in parts}) > 1:
                raise ValueError(
                    f"errors of shapes {[tuple(part.shape[1:]) for part in parts]} (horizon, target) cannot "
                    "be pooled: the models forecast different futures"
                )
            magnitudes[index] = torch.cat(parts)
        windows = {i: self.windows.get(i, 0) + other.windows.get(i, 0) for i in patterns}
        return StandardisedErrors(self.names, windows, magnitudes)


@torch.no_grad()
def standardised_errors(
    model, batches: Iterable[TensorDictBase], device: torch.device | str = "cpu"
) -> StandardisedErrors:
    """``model``'s standardised errors on ``batches`` (CPU batches with ``"target"``) under its scale as
    trained: its factors are reset to ones first, in place (the model is left uncalibrated, moved to
    ``device`` and in eval mode). Each (window, pattern) pair the evaluation's presence subsets give
    counts once."""
    calibration = _calibration_module(model)
    names = [s.name for s in model.modalities]
    calibration.reset()
    model.to(device).eval()
    windows, residuals = _standardised_residuals(model, calibration, batches, names, device)
    if not windows:
        raise ValueError("no window to fit the scale factors on: the batches are empty")
    return StandardisedErrors(names, dict(windows), {i: torch.cat(parts) for i, parts in residuals.items()})


def fit_scale_calibration(
    model,
    batches: Iterable[TensorDictBase],
    min_windows: int = DEFAULT_MIN_WINDOWS,
    device: torch.device | str = "cpu",
    method: str = DEFAULT_METHOD,
    per_step: bool = False,
) -> list[PatternFit]:
    """Fit ``model.scale_calibration`` in place on its own errors on ``batches`` (see module docstring);
    one entry per pattern seen.

    ``batches``: CPU batches with ``"target"`` (e.g. ``WindowDataset.loader("val", ...)``);
    ``method``: a key of :data:`CALIBRATION_METHODS`; ``per_step``: also fit the step factors."""
    _check_fit_settings(min_windows, method)  # before the pass over the batches
    return fit_to_errors(model, standardised_errors(model, batches, device), min_windows, method, per_step)


def _check_fit_settings(min_windows: int, method: str) -> None:
    if min_windows < 1:
        raise ValueError(f"min_windows must be >= 1, found {min_windows}")
    if method not in CALIBRATION_METHODS:
        raise ValueError(
            f"unknown calibration method {method!r}: choose among {', '.join(CALIBRATION_METHODS)}"
        )


@torch.no_grad()  # the factors are written in place: never from values carrying a graph
def fit_to_errors(
    model,
    errors: StandardisedErrors,
    min_windows: int = DEFAULT_MIN_WINDOWS,
    method: str = DEFAULT_METHOD,
    per_step: bool = False,
) -> list[PatternFit]:
    """Fit ``model.scale_calibration`` in place to standardised ``errors``: its own
    (:func:`fit_scale_calibration`), or those of models like it on data none of them trained on, when
    the data the model will meet differs from its val split as a held-out scene differs from the
    training scenes (a cross-fit: the factors say how much wider than its trained scale such a model's
    errors are there). One entry per pattern of ``errors``; the coverages are those of ``errors``."""
    calibration = _calibration_module(model)
    _check_fit_settings(min_windows, method)
    names = [s.name for s in model.modalities]
    if errors.names != names:
        raise ValueError(f"errors over modalities {errors.names} cannot calibrate a model of {names}")
    if not errors.windows:
        raise ValueError("no window to fit the scale factors on: the errors are empty")
    horizon = calibration.step_factors.shape[1]
    if other := sorted({m.shape[1] for m in errors.magnitudes.values()} - {horizon}):
        raise ValueError(
            f"errors over {other[0]} horizon steps cannot calibrate a model forecasting {horizon} steps"
        )
    family = output_distribution_of(model)
    with_curve = method in LEVEL_CURVE_METHODS

    def factor_of(values: torch.Tensor) -> float:
        return CALIBRATION_METHODS[method](values, family)

    calibration.reset()
    windows, magnitudes = errors.windows, errors.magnitudes
    pooled = sum(windows.values()) >= min_windows
    every_value = torch.cat([m.flatten() for m in magnitudes.values()])
    pooled_factor = factor_of(every_value) if pooled else 1.0
    pooled_curve = level_curve(every_value / pooled_factor, family) if pooled and with_curve else None
    fits = []
    for index in sorted(windows):
        fitted = windows[index] >= min_windows
        values = magnitudes[index]
        factor = factor_of(values.flatten()) if fitted else pooled_factor
        calibration.factors[index] = factor
        if per_step and fitted:
            by_step = torch.tensor([factor_of(values[:, step].flatten()) for step in range(values.shape[1])])
            calibration.step_factors[index] = by_step / factor
        applied = calibration.factors[index] * calibration.step_factors[index]  # as the model multiplies
        # On the CPU, where the errors are: the model (its factors) may be on another device.
        applied = applied.double().cpu().view(1, -1, *[1] * (values.dim() - 2))
        curve = level_curve(values / applied, family) if fitted and with_curve else pooled_curve
        if curve is not None:
            calibration.level_factors[index] = curve
        half_widths = level_half_widths(
            calibration.level_factors[index].double().cpu(), (LEVEL_50, LEVEL_90), family
        )
        before = [family.half_width(level) for level in (LEVEL_50, LEVEL_90)]
        fits.append(
            PatternFit(
                pattern=pattern_name(index, names),
                index=index,
                windows=windows[index],
                factor=float(calibration.factors[index]),
                fitted=fitted,
                coverage_90_before=float((values <= before[1]).double().mean()),
                coverage_90_after=float((values <= half_widths[1] * applied).double().mean()),
                pooled=not fitted and pooled,
                step_factors=applied.flatten().tolist() if per_step and fitted else None,
                coverage_50_before=float((values <= before[0]).double().mean()),
                coverage_50_after=float((values <= half_widths[0] * applied).double().mean()),
                level_factors=calibration.level_factors[index].tolist() if curve is not None else None,
            )
        )
    return fits


def _standardised_residuals(model, calibration, batches, names: list[str], device):
    """Per presence pattern: the window count and every ``|z|`` (``z = (y - loc) / scale``) as
    ``[windows, T, ...]``, over every (window, pattern) pair the evaluation's presence subsets give,
    each once."""
    subsets = list(presence_subsets(names))
    bits = calibration.bits.cpu()
    windows = defaultdict(int)
    residuals: dict[int, list[torch.Tensor]] = defaultdict(list)
    for batch in batches:
        if batch.shape[0] == 0:
            continue
        present = _presence(batch, names, "a batch")
        rows = torch.arange(batch.shape[0])
        seen = torch.zeros(batch.shape[0], 2 ** len(names), dtype=torch.bool)
        for _, subset in subsets:
            kept = present & torch.tensor([subset[n] for n in names])
            nominal = (kept.long() * bits).sum(-1)
            new = kept.any(1) & ~seen[rows, nominal]
            if not new.any():
                continue
            seen[rows[new], nominal[new]] = True
            window = apply_presence_subset(batch[new], subset)
            out = model(window.exclude(keys.TARGET).to(device))
            # The presence the model used (nonfinite="absent" may have made a modality absent).
            pattern = calibration.pattern_index(_presence(out, names, "the model's output")).cpu()
            loc, scale = out.get(keys.FORECAST_LOC).cpu(), out.get(keys.FORECAST_SCALE).cpu()
            z = ((window.get(keys.TARGET) - loc) / scale).double()
            for index in pattern.unique().tolist():
                mine = pattern == index
                windows[index] += int(mine.sum())
                residuals[index].append(z[mine].abs())
    return windows, residuals


def calibration_record(
    model,
    fits: list[PatternFit],
    split: str,
    min_windows: int,
    data_root,
    method: str,
    per_step: bool = False,
) -> dict:
    """What is stored with the model about its fit (``model.calibration``): the split, the
    settings, every pattern's fit and the factors it describes (so a reader can tell whether the
    weights still hold them)."""
    calibration = _calibration_module(model)
    return {
        "split": split,
        "method": method,
        "per_step": per_step,
        "min_windows": min_windows,
        "data_root": str(data_root),
        "eval_latent": getattr(model.config, "eval_latent", None),
        "output_distribution": output_distribution_of(model).describe(),
        "patterns": [asdict(fit) for fit in fits],
        "factors": calibration.factors.tolist(),
        "step_factors": calibration.step_factors.tolist(),
        "levels": list(LEVELS),
        "level_factors": calibration.level_factors.tolist(),
    }


def _describes(record: dict, calibration) -> bool:
    """``record`` holds the factors ``calibration`` holds (a record written before the step factors or
    the level curves existed: with step factors, or level curves, of ones, the factors then)."""
    factors = calibration.factors.cpu()
    if not torch.equal(torch.tensor(record.get("factors", []), dtype=factors.dtype), factors):
        return False
    for name, held in (
        ("step_factors", calibration.step_factors),
        ("level_factors", calibration.level_factors),
    ):
        recorded = record.get(name)
        held = held.cpu()
        if recorded is None and not bool((held == 1).all()):
            return False
        if recorded is not None and not torch.equal(torch.tensor(recorded, dtype=held.dtype), held):
            return False
    return True


def calibration_in_use(model) -> dict | None:
    """``model.calibration`` if it describes the factors the model holds now; ``None`` when the
    factors are ones and no fit is recorded. Factors without a matching record (written by hand,
    or the record of another fit) give ``{"split": None, ...}``: recalibrated, fit unknown."""
    calibration = _calibration_module(model)
    record = getattr(model, "calibration", None)
    if record is not None and _describes(record, calibration):
        return record
    if calibration.is_identity():
        return None
    return {
        "split": None,
        "per_step": calibration.has_step_factors(),
        "level_curve": calibration.has_level_curve(),
        "factors": calibration.factors.tolist(),
        "step_factors": calibration.step_factors.tolist(),
        "levels": list(LEVELS),
        "level_factors": calibration.level_factors.tolist(),
    }


def calibration_header(record: dict | None) -> str:
    """The results.md line saying how the forecast's scale was calibrated ("" when it was not)."""
    if record is None:
        return ""
    # Records written before the step factors existed fitted one factor per pattern.
    scope = "per presence pattern and horizon step" if record.get("per_step") else "per presence pattern"
    curve = record.get("level_curve", record_method(record) in LEVEL_CURVE_METHODS)
    curve = "; a level curve per pattern, read by the intervals and the CRPS" if curve else ""
    if record["split"] is None:
        return f"Forecast scale: recalibrated {scope} (the fit is not recorded with the model{curve})\n\n"
    fitted = sum(p["fitted"] for p in record["patterns"])
    return (
        f"Forecast scale: recalibrated {scope} on the {record['split']} split "
        f"(`mmf-rl calibrate`, method={record_method(record)}{curve}; {fitted} of {len(record['patterns'])} "
        f"patterns fitted, min_windows={record['min_windows']})\n\n"
    )


def record_method(record: dict) -> str:
    """The method of a recorded fit; records written before the choice existed were temperatures."""
    return record.get("method", "temperature")


def unfit_for_latent(model) -> str | None:
    """Reset the factors (to the scale as trained) when they were fitted under another eval latent
    than the model now decodes with (e.g. ``mmf-rl eval eval_latent=predictive`` of a model
    calibrated with ``mean``): they describe another forecast. Returns a note saying so, or None."""
    record = getattr(model, "calibration", None)
    now = getattr(model.config, "eval_latent", None)
    if record is None or record.get("eval_latent") == now:
        return None
    _calibration_module(model).reset()
    model.calibration = None
    return (
        f"scale factors not applied: they were fitted with eval_latent={record.get('eval_latent')} and this "
        f"evaluation decodes with eval_latent={now} (refit: mmf-rl calibrate, after saving the model with it)"
    )


def fit_table(fits: list[PatternFit], split: str) -> str:
    """The per-pattern table ``mmf-rl calibrate`` prints; with step factors, a column of each step's
    factor; with level curves, a column of each pattern's curve (its half width at each level of
    :data:`~mmf_rl.models.scale_calibration.LEVELS` over the family's, 2 decimals)."""
    per_step = any(fit.step_factors is not None for fit in fits)
    curves = any(fit.level_factors is not None for fit in fits)
    percents = ", ".join(f"{100 * level:g}" for level in LEVELS)
    columns = ["pattern", f"{split} windows", "factor", *["factor per step"] * per_step]
    columns += [f"level curve ({percents}%)"] * curves
    columns += ["coverage 50% before -> after", "coverage 90% before -> after"]
    lines = [f"| {' | '.join(columns)} |", "|" + "---|" * len(columns)]
    for fit in fits:
        factor = f"{fit.factor:.3f}"
        if fit.pooled:
            factor += " (pooled: too few windows)"
        elif not fit.fitted:
            factor = "1 (kept: too few windows)"
        if per_step:
            steps = ", ".join(f"{f:.2f}" for f in fit.step_factors) if fit.step_factors else "as the factor"
            factor += f" | {steps}"
        if curves:
            curve = " ".join(f"{f:.2f}" for f in fit.level_factors) if fit.level_factors else "the family's"
            factor += f" | {curve}{' (pooled)' if fit.pooled and fit.level_factors else ''}"
        cover_50 = _before_after(fit.coverage_50_before, fit.coverage_50_after)
        cover_90 = _before_after(fit.coverage_90_before, fit.coverage_90_after)
        lines.append(f"| {fit.pattern} | {fit.windows} | {factor} | {cover_50} | {cover_90} |")
    return "\n".join(lines)


def _before_after(before: float | None, after: float | None) -> str:
    return "-" if before is None else f"{before:.3f} -> {after:.3f}"


def _same_weights(model, state: dict[str, torch.Tensor]) -> bool:
    """``state`` holds the weights of ``model``, whatever its scale factors."""
    own = {k: v for k, v in model.state_dict().items() if k not in CALIBRATION_KEYS}
    theirs = {k: v for k, v in state.items() if k not in CALIBRATION_KEYS}
    return own.keys() == theirs.keys() and all(torch.equal(v.cpu(), theirs[k]) for k, v in own.items())


def save_to_checkpoint(model, path: Path, **meta) -> Path:
    """Re-save checkpoint ``path`` at its step with the model's weights, factors and fit, and ``meta``
    over its stored meta (its ``last`` pointer unchanged)."""
    checkpoint = load_checkpoint(path)
    directory = checkpoint.path.parent
    meta = {k: v for k, v in checkpoint.meta.items() if k not in ("format_version", "step")} | meta
    meta["calibration"] = model.calibration
    last = list_checkpoints(directory)[-1:] == [checkpoint.path]
    return save_checkpoint(
        directory,
        checkpoint.step,
        {k: v.cpu() for k, v in model.state_dict().items()},
        meta=meta,
        tensors=checkpoint.tensors,
        trainer_state=checkpoint.trainer_state,
        point_last=last,
    )


def _in_hub_cache(path: Path) -> bool:
    from huggingface_hub.constants import HF_HUB_CACHE

    return path.resolve().is_relative_to(Path(HF_HUB_CACHE).resolve())


def save_calibration(model, source: TrainedModelSource) -> list[Path]:
    """Write the model's factors and fit (``model.calibration``) back where it was loaded from, and
    into the run's twin copy holding the same weights (a checkpoint's ``RUN_DIR/model`` export, an
    export's last checkpoint). Returns the paths written."""
    if source.kind == "save_pretrained":
        if _in_hub_cache(source.path):
            raise CheckpointError(
                f"{source.path} is in the Hugging Face cache, which is no place for a changed model; copy it "
                "first (hf download USER/MODEL --local-dir DIR), then calibrate DIR"
            )
        export, checkpoint = source.path, None
        checkpoints = source.path.parent / "checkpoints"
        if source.path.name == RUN_EXPORT_DIR and list_checkpoints(checkpoints):
            twin = resolve_checkpoint(checkpoints)
            if _same_weights(model, load_file(twin / MODEL_FILE)):
                checkpoint = twin
    else:
        checkpoint, export = source.path, None
        twin = source.path.parent.parent / RUN_EXPORT_DIR
        weights = twin / SAFETENSORS_SINGLE_FILE
        if weights.is_file() and _same_weights(model, load_file(weights)):
            export = twin
    written = []
    if checkpoint is not None:
        written.append(save_to_checkpoint(model, checkpoint))
    if export is not None:
        model.save_pretrained(export)
        written.append(export)
    return written


def calibrate_after_training(model, data, checkpoint: Path, device: torch.device | str = "cpu") -> str:
    """``mmf-rl train calibrate=true``: fit the trained ``model`` on its run's val split (``data``, a
    ``WindowDataset``) by the default method and re-save its last ``checkpoint`` with the factors;
    the message saying what was done.
    """
    if len(data.split_windows["val"]) == 0:
        return "forecast scale not recalibrated: the val split has no window"
    fits = fit_scale_calibration(model, data.loader("val", 256), DEFAULT_MIN_WINDOWS, device)
    model.calibration = calibration_record(
        model, fits, "val", DEFAULT_MIN_WINDOWS, data.config.root, DEFAULT_METHOD
    )
    save_to_checkpoint(model, checkpoint)
    return (
        f"forecast scale recalibrated per presence pattern on the val split (method={DEFAULT_METHOD}):\n"
        f"{fit_table(fits, 'val')}"
    )
