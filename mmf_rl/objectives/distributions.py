"""Output distribution families: how a forecast's ``("forecast", "loc"/"scale")`` is read.

Every model writes a location and a positive scale per future value ``[B, T, D]``; its family
(``model.output_distribution``, saved with the model's config) says which distribution they are the
location and scale of. Everything that scores or fits the forecast reads it through the family: the
likelihood losses (``nll``, the ELBO's reconstruction, ``L_mis``'s KL and its degraded NLL), the
evaluation (NLL, central-interval coverage and width, CRPS) and the scale calibration (the coverage
factor, the NLL temperature).

* ``normal`` (the default): ``N(loc, scale²)``, ``scale`` the standard deviation; the Gaussian terms
  of :mod:`mmf_rl.objectives.common` exactly as before the families existed.
* ``laplace``: ``Laplace(loc, scale)``, density ``exp(-|y - loc| / scale) / (2 scale)``; standard
  deviation ``sqrt(2) · scale``.
* ``student_t``: Student's t with ``output_df`` degrees of freedom (fixed, a config value), location
  ``loc`` and scale ``scale``; standard deviation ``scale · sqrt(df / (df - 2))``. Heavier tails than the
  Gaussian: one scale can cover both the 50% and the 90% interval of errors whose tails are heavy.

A family is one :class:`OutputDistribution` subclass with ``@register_output_distribution(name)``:
its torch distribution (``log_prob``, sampling), the quantile of its standard member (the central
intervals), the CRPS in closed form, the KL between two members (``L_mis``) and the variance of the
standard member (a predictive mixture's moment matching, a world model's standard deviation). The
NLL temperature of the scale calibration is a 1-D minimisation of the NLL unless the family has a
closed form.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import numpy as np
import torch
from torch import distributions as D

from mmf_rl.objectives.common import gaussian_kl, gaussian_nll

DEFAULT_OUTPUT_DISTRIBUTION = "normal"
# Student's t degrees of freedom by default: 4 is the classic robust choice for a t likelihood with
# fixed df (Lange, Little & Taylor 1989): its tails are heavy (kurtosis unbounded) yet its variance is
# finite, so the forecast keeps a standard deviation (a world model's, a predictive mixture's), and
# its 50% / 90% half-width ratio (0.741 / 2.132 = 0.35) sits well below the Gaussian's (0.674 / 1.645
# = 0.41): the shape of the heavy-tailed errors of real arms, where one Gaussian scale fitted at 90%
# over-covers at 50%.
DEFAULT_OUTPUT_DF = 4.0

OUTPUT_DISTRIBUTIONS: dict[str, type[OutputDistribution]] = {}


def register_output_distribution(name: str) -> Callable[[type], type]:
    """Class decorator: the :class:`OutputDistribution` subclass it decorates is the family ``name``
    (``model.output_distribution=NAME``).

    Args:
        name (str): the family's name.

    Returns:
        The decorator; it sets the class's ``name`` and returns the class, and raises ``TypeError`` for
        a class that is not an :class:`OutputDistribution`, ``ValueError`` for a name another class took.
    """

    def register(cls: type) -> type:
        if not (isinstance(cls, type) and issubclass(cls, OutputDistribution)):
            raise TypeError(
                f"@register_output_distribution({name!r}) decorates an OutputDistribution subclass, "
                f"found {cls!r}"
            )
        if OUTPUT_DISTRIBUTIONS.get(name, cls) is not cls:
            raise ValueError(
                f"output distribution {name!r} is already registered "
                f"({OUTPUT_DISTRIBUTIONS[name].__qualname__}); pick another name"
            )
        cls.name = name
        OUTPUT_DISTRIBUTIONS[name] = cls
        return cls

    return register


class OutputDistribution:
    """A family of forecast distributions with a location and a scale (see module docstring).

    Subclasses set :meth:`distribution`, :meth:`standard_quantile`, :meth:`crps` and ``variance``; the
    KL defaults to torch's ``kl_divergence`` and the NLL temperature to a 1-D minimisation. Instances
    are immutable values: :func:`output_distribution` caches them. Every method is elementwise and
    broadcasts ``value``, ``loc`` and ``scale``.
    """

    name: ClassVar[str] = ""
    # The variance of the standard member (loc 0, scale 1): the forecast's standard deviation is
    # ``scale · sqrt(variance)``.
    variance: float = 1.0

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> OutputDistribution:
        """The family as a model config's ``output_*`` settings set it (none read by default).

        Args:
            settings (Mapping[str, Any]): the settings, e.g. ``{"output_df": 4.0}``.

        Returns:
            The family.
        """
        return cls()

    def settings(self) -> dict[str, Any]:
        """The model config settings that describe this family (``{"output_distribution": name, ...}``)."""
        return {"output_distribution": self.name}

    def describe(self) -> str:
        """A short label, e.g. ``"student_t (df 4)"``."""
        return self.name

    def distribution(self, loc: torch.Tensor, scale: torch.Tensor) -> D.Distribution:
        """The torch distribution of this family at ``(loc, scale)`` (arguments not validated)."""
        raise NotImplementedError

    def log_prob(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """Elementwise ``log p(value; loc, scale)``.

        Args:
            value (torch.Tensor): the observed values.
            loc (torch.Tensor): the location.
            scale (torch.Tensor): the scale, ``> 0``.

        Returns:
            The log-density of each element.
        """
        return self.distribution(loc, scale).log_prob(value)

    def nll(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """Elementwise ``-log p(value; loc, scale)`` (the losses' and the evaluation's NLL)."""
        return -self.log_prob(value, loc, scale)

    def standard_quantile(self, probability: float) -> float:
        """The ``probability`` quantile of the standard member (loc 0, scale 1)."""
        raise NotImplementedError

    def half_width(self, level: float) -> float:
        """The half width of the central ``level`` interval of the standard member: ``|y - loc| <=
        half_width(level) · scale`` holds with probability ``level``.

        Args:
            level (float): in ``(0, 1)``.

        Returns:
            The half width, in units of ``scale``.
        """
        return self.standard_quantile(0.5 + level / 2)

    def crps(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """Elementwise continuous ranked probability score ``∫ (F(x) - 1{x >= value})² dx`` in closed
        form (lower is better; for a point forecast, the absolute error)."""
        raise NotImplementedError

    def kl(
        self, loc_p: torch.Tensor, scale_p: torch.Tensor, loc_q: torch.Tensor, scale_q: torch.Tensor
    ) -> torch.Tensor:
        """Elementwise ``KL(p || q)`` between two members of the family (``L_mis``'s teacher ``p`` and
        student ``q``)."""
        return D.kl_divergence(self.distribution(loc_p, scale_p), self.distribution(loc_q, scale_q))

    def stddev(self, scale: torch.Tensor) -> torch.Tensor:
        """The standard deviation of the members with scale ``scale``."""
        return scale * math.sqrt(self.variance)

    def temperature(self, magnitudes: torch.Tensor) -> float:
        """The NLL-optimal factor ``s`` of the scale for standardised errors ``|z| = |y - loc| / scale``:
        ``argmin_s mean(-log p(z; 0, s))``.

        By default a 1-D minimisation (bounded Brent on ``log s``) of the mean NLL, for a family without
        a closed form; a family with one overrides this.

        Args:
            magnitudes (torch.Tensor): the values ``|z|``.

        Returns:
            The factor.
        """
        from scipy.optimize import minimize_scalar

        z = magnitudes.detach().double().flatten().cpu()
        zero = torch.zeros((), dtype=z.dtype)
        typical = max(float(z.abs().mean()), 1e-12)

        def mean_nll(log_factor: float) -> float:
            factor = torch.tensor(math.exp(log_factor), dtype=z.dtype)
            return float(self.nll(z, zero, factor).mean())

        centre = math.log(typical)
        found = minimize_scalar(
            mean_nll, bounds=(centre - 12, centre + 12), method="bounded", options={"xatol": 1e-9}
        )
        return math.exp(found.x)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.describe()!r})"


@register_output_distribution("normal")
class NormalOutput(OutputDistribution):
    """``N(loc, scale²)``: the Gaussian terms of :mod:`mmf_rl.objectives.common` (the default family).

    Examples:
        >>> import torch
        >>> from mmf_rl.objectives import output_distribution
        >>> normal = output_distribution("normal")
        >>> round(normal.half_width(0.9), 4)
        1.6449
        >>> normal.nll(torch.tensor([0.0]), torch.zeros(1), torch.ones(1))  # 0.5 log 2π
        tensor([0.9189])
    """

    variance = 1.0

    def distribution(self, loc: torch.Tensor, scale: torch.Tensor) -> D.Distribution:
        return D.Normal(loc, scale, validate_args=False)

    def log_prob(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        return -gaussian_nll(value, loc, scale)

    def nll(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        return gaussian_nll(value, loc, scale)

    def standard_quantile(self, probability: float) -> float:
        return D.Normal(0.0, 1.0).icdf(torch.tensor(probability)).item()

    def crps(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """Gneiting & Raftery (2007): ``scale · (z (2 Φ(z) - 1) + 2 φ(z) - 1 / sqrt(pi))``, ``z = (value -
        loc) / scale``; one line, so no scoring library (properscoring, scoringrules) is needed."""
        z = (value - loc) / scale
        normal = D.Normal(0.0, 1.0)
        return scale * (z * (2 * normal.cdf(z) - 1) + 2 * normal.log_prob(z).exp() - 1 / math.sqrt(math.pi))

    def kl(self, loc_p, scale_p, loc_q, scale_q) -> torch.Tensor:
        return gaussian_kl(loc_p, scale_p, loc_q, scale_q)

    def stddev(self, scale: torch.Tensor) -> torch.Tensor:
        return scale

    def temperature(self, magnitudes: torch.Tensor) -> float:
        """In closed form: ``sqrt(mean(z²))``."""
        return math.sqrt(float(magnitudes.square().mean()))


@register_output_distribution("laplace")
class LaplaceOutput(OutputDistribution):
    """``Laplace(loc, scale)``: density ``exp(-|y - loc| / scale) / (2 scale)``, standard deviation
    ``sqrt(2) · scale``; its NLL is an L1 loss in ``loc``.

    Examples:
        >>> import torch
        >>> from mmf_rl.objectives import output_distribution
        >>> laplace = output_distribution("laplace")
        >>> round(laplace.half_width(0.5), 4)  # log 2
        0.6931
        >>> laplace.crps(torch.tensor([0.0]), torch.zeros(1), torch.ones(1))  # 1 - 3/4
        tensor([0.2500])
    """

    variance = 2.0

    def distribution(self, loc: torch.Tensor, scale: torch.Tensor) -> D.Distribution:
        return D.Laplace(loc, scale, validate_args=False)

    def standard_quantile(self, probability: float) -> float:
        return D.Laplace(0.0, 1.0).icdf(torch.tensor(probability, dtype=torch.float64)).item()

    def crps(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """``|y - loc| + scale · exp(-|y - loc| / scale) - 3 scale / 4``."""
        error = (value - loc).abs()
        return error + scale * torch.exp(-error / scale) - 0.75 * scale

    def temperature(self, magnitudes: torch.Tensor) -> float:
        """In closed form: ``mean(|z|)``."""
        return float(magnitudes.abs().double().mean())


@register_output_distribution("student_t")
class StudentTOutput(OutputDistribution):
    """Student's t with ``df`` degrees of freedom, location ``loc`` and scale ``scale``.

    ``log_prob`` is torch's ``StudentT``; torch has no Student-t CDF or quantile (``StudentT.icdf``
    and ``cdf`` are not implemented, nor the regularised incomplete beta they need), so the central
    interval's quantile (a number per level, computed once) and the CDF inside the CRPS (evaluation
    only, no gradient) are scipy's. The CRPS is the closed form of Jordan, Krüger & Lerch (2019,
    scoringrules' ``crps_t``). The KL between two members (``L_mis``) has no closed form: it is
    ``log(s_q / s_p) + (df + 1) / 2 · E_u[log(1 + ((Δ + s_p u) / s_q)² / df) - log(1 + u² / df)]``,
    ``Δ = loc_p - loc_q``, ``u ~ t_df``, the expectation by 32-point Gauss-Legendre quadrature over
    the quantiles of ``u`` (fixed nodes, so it is deterministic, differentiable and exactly 0 for
    ``p = q``; within 0.2% of adaptive quadrature for ``df`` 2.5 to 30).

    Args:
        df (float, optional): the degrees of freedom, ``> 2`` (a finite variance: the forecast keeps a
            standard deviation). Defaults to ``4`` (``DEFAULT_OUTPUT_DF``, see there).

    Raises:
        ValueError: ``df <= 2``.

    Examples:
        >>> import torch
        >>> from mmf_rl.objectives import output_distribution
        >>> student = output_distribution("student_t", output_df=4.0)
        >>> round(student.half_width(0.9), 4)
        2.1318
        >>> student.describe()
        'student_t (df 4)'
    """

    QUADRATURE_NODES = 32

    def __init__(self, df: float = DEFAULT_OUTPUT_DF):
        if isinstance(df, bool) or not isinstance(df, (int, float)) or not df > 2:
            raise ValueError(
                f"output_df must be a number > 2 (the Student-t forecast needs a finite variance), "
                f"found {df!r}"
            )
        self.df = float(df)
        self.variance = self.df / (self.df - 2)

    @classmethod
    def from_settings(cls, settings: Mapping[str, Any]) -> StudentTOutput:
        """The degrees of freedom are the config's ``output_df`` (default ``DEFAULT_OUTPUT_DF``)."""
        return cls(settings.get("output_df", DEFAULT_OUTPUT_DF))

    def settings(self) -> dict[str, Any]:
        return {"output_distribution": self.name, "output_df": self.df}

    def describe(self) -> str:
        return f"{self.name} (df {self.df:g})"

    def distribution(self, loc: torch.Tensor, scale: torch.Tensor) -> D.Distribution:
        return D.StudentT(self.df, loc, scale, validate_args=False)

    def standard_quantile(self, probability: float) -> float:
        from scipy.stats import t

        return float(t.ppf(probability, self.df))

    def _cdf(self, z: torch.Tensor) -> torch.Tensor:
        from scipy.special import stdtr

        values = stdtr(self.df, z.detach().cpu().double().numpy())
        return torch.as_tensor(values, dtype=z.dtype, device=z.device)

    @functools.cached_property
    def _crps_constant(self) -> float:
        """``2 sqrt(df) B(1/2, df - 1/2) / ((df - 1) B(1/2, df / 2)²)``."""
        from scipy.special import beta

        df = self.df
        return 2 * math.sqrt(df) * beta(0.5, df - 0.5) / ((df - 1) * beta(0.5, df / 2) ** 2)

    def crps(self, value: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """``scale · (z (2 F(z) - 1) + 2 f(z) (df + z²) / (df - 1) - 2 sqrt(df) B(1/2, df - 1/2) / ((df - 1)
        B(1/2, df / 2)²))``, ``z = (value - loc) / scale``, ``F``, ``f`` the standard t's CDF and density
        (Jordan, Krüger & Lerch 2019). No gradient: ``F`` is scipy's."""
        z = (value - loc) / scale
        density = (
            self.distribution(torch.zeros((), dtype=z.dtype), torch.ones((), dtype=z.dtype)).log_prob(z).exp()
        )
        df = self.df
        return scale * (
            z * (2 * self._cdf(z) - 1) + 2 * density * (df + z.square()) / (df - 1) - self._crps_constant
        )

    @functools.cached_property
    def _quadrature(self) -> tuple[torch.Tensor, torch.Tensor, float]:
        """The quadrature's nodes ``u_k`` (quantiles of ``t_df``), weights ``w_k`` (summing to 1) and
        ``sum_k w_k log(1 + u_k² / df)``."""
        from scipy.stats import t

        points, weights = np.polynomial.legendre.leggauss(self.QUADRATURE_NODES)
        nodes = t.ppf((points + 1) / 2, self.df)
        weights = weights / 2
        own = float(np.sum(weights * np.log1p(nodes**2 / self.df)))
        return torch.from_numpy(nodes), torch.from_numpy(weights), own

    def kl(self, loc_p, scale_p, loc_q, scale_q) -> torch.Tensor:
        nodes, weights, own = self._quadrature
        shape = (-1, *[1] * max(loc_p.dim(), scale_p.dim(), loc_q.dim(), scale_q.dim()))
        nodes = nodes.to(loc_p).view(shape)
        weights = weights.to(loc_p).view(shape)
        standardised = (loc_p - loc_q + scale_p * nodes) / scale_q  # [K, ...]
        cross = (weights * torch.log1p(standardised.square() / self.df)).sum(0)
        return (scale_q / scale_p).log() + (self.df + 1) / 2 * (cross - own)


@functools.cache
def _family(name: str, settings: tuple[tuple[str, Any], ...]) -> OutputDistribution:
    return OUTPUT_DISTRIBUTIONS[name].from_settings(dict(settings))


def output_distribution(name: str = DEFAULT_OUTPUT_DISTRIBUTION, **settings: Any) -> OutputDistribution:
    """The registered family ``name``, with the model config settings it reads (``output_df``).

    Args:
        name (str, optional): ``"normal"`` (default), ``"laplace"``, ``"student_t"`` or another registered
            family.
        **settings (Any): the model config's other ``output_*`` settings (``output_df=4.0``); a family
            reads those it has and ignores the others.

    Returns:
        The family (a cached, immutable value).

    Raises:
        ValueError: an unknown ``name``, or a setting the family refuses (``output_df <= 2`` for
            ``student_t``).

    Examples:
        >>> import torch
        >>> from mmf_rl.objectives import output_distribution
        >>> laplace = output_distribution("laplace")
        >>> laplace.nll(torch.tensor([1.0]), torch.zeros(1), torch.ones(1))  # log 2 + 1
        tensor([1.6931])
        >>> output_distribution("student_t", output_df=3).describe()
        'student_t (df 3)'
    """
    if name not in OUTPUT_DISTRIBUTIONS:
        raise ValueError(
            f"unknown output distribution {name!r}; expected one of {sorted(OUTPUT_DISTRIBUTIONS)} "
            "(a new family is an OutputDistribution subclass with @register_output_distribution(name))"
        )
    return _family(name, tuple(sorted(settings.items())))


def output_settings(config: Any) -> dict[str, Any]:
    """The ``output_*`` settings of a model config (``output_distribution``, ``output_df``), ``{}`` for
    ``None`` or an object without them.

    Args:
        config (Any): a model config (a dataclass), or ``None``.

    Returns:
        ``{name: value}``.
    """
    found = vars(config) if hasattr(config, "__dict__") else {}
    return {name: value for name, value in found.items() if name.startswith("output_")}


def output_distribution_of(model: Any) -> OutputDistribution:
    """The family a model's forecast is read with: its config's ``output_distribution`` (and the
    ``output_*`` settings the family reads); ``normal`` for a module whose config has none (a
    hand-written forecaster, a model saved before the option: its family was the Gaussian).

    Args:
        model (Any): a model (its ``config`` is read), or a model config itself.

    Returns:
        The family.

    Raises:
        ValueError: the config names an unknown family or a setting it refuses.

    Examples:
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig
        >>> from mmf_rl.objectives import output_distribution_of
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> output_distribution_of(ForecasterConfig([force], output_distribution="laplace")).name
        'laplace'
    """
    config = model if hasattr(model, "output_distribution") else getattr(model, "config", None)
    settings = output_settings(config)
    return output_distribution(settings.pop("output_distribution", DEFAULT_OUTPUT_DISTRIBUTION), **settings)
