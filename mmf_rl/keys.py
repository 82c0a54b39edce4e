"""The TensorDict key contract shared by data, models, losses and RL glue.

Every module imports key names from here; none retypes them. A batch has batch size ``[B]``:

===================================  ===================  ==================================================
key                                  shape                meaning
===================================  ===================  ==================================================
``("obs", m)``                       ``[B, H, *feat_m]``  past window of modality ``m`` (``[B, *feat_m]`` for
                                                          a single-vector modality)
``("present", m)``                   ``[B]`` bool         modality ``m`` is available for this sample (at
                                                          one step of its window at least)
``("present_steps", m)``             ``[B, H]`` bool      optional: the steps of the window where ``m`` is
                                                          available; without it, every step of a present
                                                          modality is
``"target"``                         ``[B, T, D]``        future of the forecast variable (normalised frame)
``"target_past"``                    ``[B, H, D]``        its history, when the data provides it
``"future_action"``                  ``[B, S, A]``        actions applied over the horizon (``S = T·stride``
                                                          frames from the last observed one; normalised),
                                                          read by action-conditioned models (world models)
``("forecast", "loc" | "scale")``    ``[B, T, D]``        forecast location and scale (a diagonal Gaussian
                                                          unless the model's ``output_distribution`` says)
``("forecast", "samples")``          ``[B, K, T, D]``     K forecasts, one per latent sample (best-of-K)
``("forecast", "valid")``            ``[B]`` bool         False where no modality was present (RL glue: the
                                                          forecast is then the target's training prior)
``("forecast_dropped", ...)``        ``[B, T, D]``        forecast with the modalities in ``("drop", m)``
                                                          removed
``("drop", m)``                      ``[B]`` bool         modality removed for the missing-modality loss
``("drop_steps", m)``                ``[B, H]`` bool      optional: steps of ``m`` removed for that loss's
                                                          degraded input only (a tail cut)
``("posterior" | "prior", ...)``     ``[B, d_z]``         latent distributions (``loc``/``scale``)
``("prior_dropped", ...)``           ``[B, d_z]``         learned prior ``p(z|X)`` of the input without the
                                                          ``("drop", m)`` modalities
``"decode_from_prior"``              ``[B]`` bool         request: also decode every row from ``z ~ p(z|X)``
                                                          in training (the GSNN term of the ELBO loss)
``"decode_prior_draws"``             ``[B, K]`` bool      request: also decode ``K`` draws ``z ~ p(z|X)`` per
                                                          row in training (the best-of-K term of the ELBO
                                                          loss); only its shape is read
``("forecast_from_prior", ...)``     ``[B, T, D]``        the forecast of the ``"decode_from_prior"`` draw
                                                          (``loc``/``scale``); ``"samples"`` ``[B, K, T, D]``:
                                                          the means of the ``"decode_prior_draws"`` ones
``"latent"``                         ``[B, d_z]``         the latent code the forecast was decoded from
``"loss_*"``                         scalar               one loss term each, summed by the trainer
===================================  ===================  ==================================================

Rules: a sample needs at least one present modality; the value stored under an absent modality (or
under an absent step of a present one) never changes any output; output shapes never depend on
presence. A batch has at least one sample (an empty batch is a clear error, not empty outputs: a
loss or metric over zero samples has no value, so the caller skips it). NaN or ±Inf under a
*present* modality is an error naming the key and the samples, or, with a model's
``nonfinite="absent"``, makes that modality absent for those samples (:func:`validate_batch` checks,
:func:`mark_nonfinite_absent` applies); the RL glue always does the latter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

import torch

OBS = "obs"
PRESENT = "present"
PRESENT_STEPS = "present_steps"
DROP = "drop"
DROP_STEPS = "drop_steps"
TARGET = "target"
TARGET_PAST = "target_past"
FUTURE_ACTION = "future_action"
HISTORY = "history"  # RL glue: an env's current model input window, a sub-TensorDict of this contract
LATENT = "latent"

LOC = "loc"
SCALE = "scale"
SAMPLES = "samples"

FORECAST = "forecast"
FORECAST_DROPPED = "forecast_dropped"
FORECAST_FROM_PRIOR = "forecast_from_prior"
DECODE_FROM_PRIOR = "decode_from_prior"
DECODE_PRIOR_DRAWS = "decode_prior_draws"
POSTERIOR = "posterior"
PRIOR = "prior"
PRIOR_DROPPED = "prior_dropped"

FORECAST_LOC = (FORECAST, LOC)
FORECAST_SCALE = (FORECAST, SCALE)
FORECAST_SAMPLES = (FORECAST, SAMPLES)
FORECAST_VALID = (FORECAST, "valid")
FORECAST_AGE = (FORECAST, "age")  # env steps since the forecast served was made (a latched one)
FORECAST_DROPPED_LOC = (FORECAST_DROPPED, LOC)
FORECAST_DROPPED_SCALE = (FORECAST_DROPPED, SCALE)
FORECAST_FROM_PRIOR_LOC = (FORECAST_FROM_PRIOR, LOC)
FORECAST_FROM_PRIOR_SCALE = (FORECAST_FROM_PRIOR, SCALE)
FORECAST_FROM_PRIOR_SAMPLES = (FORECAST_FROM_PRIOR, SAMPLES)
POSTERIOR_LOC = (POSTERIOR, LOC)
POSTERIOR_SCALE = (POSTERIOR, SCALE)
PRIOR_LOC = (PRIOR, LOC)
PRIOR_SCALE = (PRIOR, SCALE)
PRIOR_DROPPED_LOC = (PRIOR_DROPPED, LOC)
PRIOR_DROPPED_SCALE = (PRIOR_DROPPED, SCALE)


def obs_key(modality: str) -> tuple[str, str]:
    """The key of a modality's observation window.

    Args:
        modality (str): the modality's name.

    Returns:
        ``("obs", modality)``.
    """
    return (OBS, modality)


def present_key(modality: str) -> tuple[str, str]:
    """The key of a modality's per-sample presence flag.

    Args:
        modality (str): the modality's name.

    Returns:
        ``("present", modality)``.
    """
    return (PRESENT, modality)


def present_steps_key(modality: str) -> tuple[str, str]:
    """The key of a modality's per-step presence flags (optional in a batch).

    Args:
        modality (str): the modality's name.

    Returns:
        ``("present_steps", modality)``.
    """
    return (PRESENT_STEPS, modality)


def zero_absent_steps(obs: torch.Tensor, present_steps: torch.Tensor) -> torch.Tensor:
    """Zero the absent steps of a window, so the value stored under an absent step never reaches an
    encoder.

    Args:
        obs (torch.Tensor): a window ``[B, H, *feat]``.
        present_steps (torch.Tensor): ``bool [B, H]``, False at the absent steps.

    Returns:
        A tensor like ``obs`` with the absent steps set to zero.

    Raises:
        ValueError: ``present_steps`` is not ``[B, H]`` of the window (e.g. a single-vector modality).
    """
    if obs.dim() < 2 or tuple(present_steps.shape) != tuple(obs.shape[:2]):
        raise ValueError(
            f"present_steps {tuple(present_steps.shape)} must be [B, H] of the window {tuple(obs.shape)}; "
            "per-step presence applies to a windowed modality (sequence or image), not a single vector"
        )
    mask = present_steps.view(*present_steps.shape, *[1] * (obs.dim() - 2))
    return torch.where(mask, obs, torch.zeros((), dtype=obs.dtype, device=obs.device))


def drop_key(modality: str) -> tuple[str, str]:
    """The key of the per-sample mask that removes a modality for the missing-modality loss.

    Args:
        modality (str): the modality's name.

    Returns:
        ``("drop", modality)``.
    """
    return (DROP, modality)


def drop_steps_key(modality: str) -> tuple[str, str]:
    """The key of the per-step mask that removes steps of a modality from that loss's degraded input.

    Args:
        modality (str): the modality's name.

    Returns:
        ``("drop_steps", modality)``.
    """
    return (DROP_STEPS, modality)


def drop_masks(td, modalities) -> torch.Tensor | None:
    """The batch's ``("drop", m)`` masks (``L_mis``'s student input), stacked in the modalities' order.

    Args:
        td (TensorDictBase): a batch ``[B]`` following this contract.
        modalities (Sequence[ModalitySpec]): the model's modalities, in order.

    Returns:
        ``bool [B, M]``, or ``None`` when the batch has no ``("drop", m)`` mask.

    Raises:
        KeyError: the batch has the masks of some modalities but not of all (the error names them).
    """
    drop_keys = [drop_key(s.name) for s in modalities]
    found = [k in td.keys(include_nested=True) for k in drop_keys]
    if not any(found):
        return None
    if not all(found):
        missing = [k for k, f in zip(drop_keys, found, strict=True) if not f]
        raise KeyError(f"batch has some ('drop', m) masks but not {missing}; give one for every modality")
    return torch.stack([td.get(k) for k in drop_keys], dim=1)


ModalityKind = Literal["image", "sequence", "vector"]
MODALITY_KINDS: tuple[str, ...] = get_args(ModalityKind)
# What a model does with NaN/Inf under a present modality: refuse the batch, or read it as absent.
NonFiniteRule = Literal["raise", "absent"]
NONFINITE_RULES = ("raise", "absent")

# The encoder each kind gets unless the spec names another one. Sequences: the flattened window
# through an MLP, which keeps each step's detail a GRU summary loses (measured better or tied on
# every recording tried; see docs/results.md). The encoders themselves, and which
# kinds each accepts, are registered in mmf_rl.models.encoders (checked when a model is built).
DEFAULT_ENCODER: dict[str, str] = {"image": "conv", "sequence": "mlp", "vector": "mlp"}


@dataclass(frozen=True)
class ModalitySpec:
    """What one modality is: its name, kind, per-step feature shape and encoder.

    Args:
        name (str): the modality's name, the ``m`` of its keys ``("obs", m)``, ``("present", m)``.
        kind (str): ``"image"``: a window of RGB frames, ``uint8 [B, H, C, h, w]``, with
            ``shape = (C, h, w)``; ``"sequence"``: a window of vectors, ``float32 [B, H, d]``, with
            ``shape = (d,)``; ``"vector"``: one vector per sample, ``float32 [B, d]``, with
            ``shape = (d,)``.
        shape (tuple[int, ...]): the per-step feature shape (see ``kind``).
        encoder (str, optional): the name of an encoder registered in :mod:`mmf_rl.models.encoders`
            for this kind (checked when a model is built); ``None``: the kind's default
            (``DEFAULT_ENCODER``). Built in: ``conv`` (frames stacked on channels: cheap, and motion
            is visible to the first layer) or ``conv_gru`` (per-frame ConvNet + GRU) for images,
            ``gru`` or ``mlp`` (flattened window) for sequences, ``deepsets`` (pooled by mean and max)
            or ``set_attention`` (pooled by attention) for sequences of ``K`` agent slots per step
            (both invariant to slot order), ``mlp`` for vectors.
        required (bool, optional): every sample has it: the data pipeline leaves out the windows
            without it (and refuses a recording whose files for it are missing), and
            :class:`~mmf_rl.objectives.DiverseSamplingLoss` never drops it. Defaults to ``False``.
        encoder_kwargs (dict, optional): keyword arguments of the encoder (e.g. ``channels`` of
            ``conv``). Not part of equality or the hash.

    Raises:
        ValueError: an unknown ``kind``, or a ``shape`` of the wrong rank or with a dim below 1.

    Examples:
        >>> from mmf_rl.keys import ModalitySpec
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> force.encoder, force.obs_key, force.obs_shape(history=4)
        ('mlp', ('obs', 'force'), (4, 6))
        >>> ModalitySpec("camera", "image", (3, 32, 32)).dtype
        torch.uint8
    """

    name: str
    kind: ModalityKind
    shape: tuple[int, ...]
    encoder: str | None = None
    required: bool = False
    encoder_kwargs: dict = field(default_factory=dict, hash=False, compare=False)

    def __post_init__(self):
        if self.kind not in MODALITY_KINDS:
            raise ValueError(
                f"modality {self.name!r}: unknown kind {self.kind!r}; "
                f"expected one of {sorted(MODALITY_KINDS)}"
            )
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        expected_rank = 3 if self.kind == "image" else 1
        if len(self.shape) != expected_rank or min(self.shape) < 1:
            raise ValueError(
                f"modality {self.name!r} ({self.kind}): shape must have {expected_rank} positive "
                f"dims ({'(C, h, w)' if self.kind == 'image' else '(d,)'}), found {self.shape}"
            )
        object.__setattr__(self, "encoder", self.encoder or DEFAULT_ENCODER[self.kind])

    @property
    def obs_key(self) -> tuple[str, str]:
        """``("obs", name)``."""
        return obs_key(self.name)

    @property
    def present_key(self) -> tuple[str, str]:
        """``("present", name)``."""
        return present_key(self.name)

    @property
    def dtype(self) -> torch.dtype:
        """The observation's dtype: ``uint8`` for images, else ``float32``."""
        return torch.uint8 if self.kind == "image" else torch.float32

    def obs_shape(self, history: int) -> tuple[int, ...]:
        """Shape of one sample's observation (without the batch dim).

        Args:
            history (int): ``H``, steps per window (unused by a ``"vector"`` modality).

        Returns:
            ``(H, *shape)``, or ``shape`` for a ``"vector"`` modality.
        """
        return self.shape if self.kind == "vector" else (history, *self.shape)

    def to_dict(self) -> dict:
        """The spec as a plain dict (for a saved config); :meth:`from_dict` reads it back."""
        return {
            "name": self.name,
            "kind": self.kind,
            "shape": list(self.shape),
            "encoder": self.encoder,
            "required": self.required,
            "encoder_kwargs": dict(self.encoder_kwargs),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ModalitySpec:
        """The spec :meth:`to_dict` wrote.

        Args:
            d (dict): the spec's fields (``shape`` as a list or tuple).

        Returns:
            A new :class:`ModalitySpec`.
        """
        d = dict(d)
        d["shape"] = tuple(d["shape"])
        return cls(**d)


def _describe(t: torch.Tensor) -> str:
    return f"{str(t.dtype).removeprefix('torch.')} {list(t.shape)}"


def _indices(rows: torch.Tensor) -> str:
    bad = rows.nonzero().flatten().tolist()
    return f"{bad[:10]}{'...' if len(bad) > 10 else ''}"


def nonfinite_rows(values: torch.Tensor) -> torch.Tensor:
    """The rows holding NaN or ±Inf (never any for an integer dtype).

    Args:
        values (torch.Tensor): ``[N, ...]``.

    Returns:
        ``bool [N]``, True where the row holds a non-finite value.
    """
    if not values.is_floating_point():
        return torch.zeros(values.shape[0], dtype=torch.bool, device=values.device)
    return ~torch.isfinite(values).flatten(1).all(1) if values.dim() > 1 else ~torch.isfinite(values)


def validate_batch(
    td,
    modalities: list[ModalitySpec],
    history: int,
    horizon: int | None = None,
    target_dim: int | None = None,
    require_target: bool = False,
    action_shape: tuple[int, int] | None = None,
    nonfinite: NonFiniteRule = "raise",
) -> None:
    """Check a batch against the contract, without changing it; raise errors that name the key,
    expected and found.

    Checked: the batch is not empty, every ``("obs", m)`` and ``("present", m)`` exists with the
    right dtype and shape, no present ``("obs", m)`` holds NaN or ±Inf (``nonfinite="raise"``;
    with ``"absent"`` those samples count as absent, which :func:`mark_nonfinite_absent` then
    writes into the batch), every sample has at least one present modality, ``"target"`` (if
    present or required) is ``float [B, T, D]``, and, for an action-conditioned model
    (``action_shape = (S, A)``), ``"future_action"`` is finite ``float32 [B, S, A]``.

    Args:
        td (TensorDictBase): the batch, batch size ``[B]``.
        modalities (list[ModalitySpec]): the model's modalities.
        history (int): ``H``, steps per window.
        horizon (int, optional): ``T`` the target must have; ``None`` accepts any.
        target_dim (int, optional): ``D`` the target must have; ``None`` accepts any.
        require_target (bool, optional): a batch without ``"target"`` is an error (training).
            Defaults to ``False``.
        action_shape (tuple[int, int], optional): ``(S, A)`` of ``"future_action"`` for an
            action-conditioned model; ``None``: not checked.
        nonfinite (str, optional): ``"raise"`` (default) or ``"absent"``, what NaN/Inf under a present
            modality means (see the module docstring).

    Raises:
        KeyError: a key of the contract is missing.
        ValueError: a wrong dtype or shape, an empty batch, a sample with no present modality,
            NaN/Inf under a present modality (with ``nonfinite="raise"``) or in the actions, or an
            unknown ``nonfinite``.
    """
    if nonfinite not in NONFINITE_RULES:
        raise ValueError(f"nonfinite must be one of {NONFINITE_RULES}, found {nonfinite!r}")
    if len(td.batch_size) != 1:
        raise ValueError(f"expected a TensorDict with batch size [B], found batch size {list(td.batch_size)}")
    batch = td.batch_size[0]
    if batch == 0:
        raise ValueError(
            "empty batch (batch size 0): there is nothing to forecast; skip empty batches before "
            "calling the model (a loss or metric over zero samples has no value)"
        )
    any_present = None
    made_absent = []
    for spec in modalities:
        nonfinite_present = _check_modality(td, spec, batch, history, nonfinite)
        present = td.get(spec.present_key)
        if nonfinite == "absent" and bool(nonfinite_present.any()):  # under "raise" there are none
            present = present & ~nonfinite_present
            made_absent.append(spec.name)
        any_present = present if any_present is None else any_present | present
    if any_present is not None and not bool(any_present.all()):
        because = f" (after NaN/Inf made {made_absent} absent)" if made_absent else ""
        raise ValueError(
            f"{int((~any_present).sum())} sample(s) have no present modality{because} (batch indices "
            f"{_indices(~any_present)}); every sample needs at least one of {[s.name for s in modalities]}"
        )
    if TARGET in td.keys() or require_target:
        _check_target(td, batch, horizon, target_dim)
    if action_shape is not None:
        _check_actions(td, batch, action_shape)


def mark_nonfinite_absent(td, modalities: list[ModalitySpec]) -> None:
    """Set ``("present", m)`` to False in ``td`` (in place) for the samples whose present
    ``("obs", m)`` holds NaN or ±Inf: the ``nonfinite="absent"`` rule, applied to a batch that
    :func:`validate_batch` accepted with that rule.

    Args:
        td (TensorDictBase): the batch, changed in place (a batch without NaN/Inf keeps its tensors).
        modalities (list[ModalitySpec]): the modalities to check.
    """
    for spec in modalities:
        present = td.get(spec.present_key)
        bad = nonfinite_rows(td.get(spec.obs_key)) & present
        if bool(bad.any()):  # a batch without NaN/Inf keeps its own tensors
            td.set(spec.present_key, present & ~bad)


def _check_modality(
    td, spec: ModalitySpec, batch: int, history: int, nonfinite: NonFiniteRule
) -> torch.Tensor:
    """Check one modality's keys; return ``[B]`` bool: its present samples holding NaN or ±Inf
    (all False unless ``nonfinite="absent"``, under which they read as absent)."""
    for key in (spec.obs_key, spec.present_key):
        if key not in td.keys(include_nested=True):
            hint = " (True where the modality is available)" if key[0] == PRESENT else ""
            raise KeyError(f"batch is missing key {key} for modality {spec.name!r}{hint}")
    obs = td.get(spec.obs_key)
    expected = (batch, *spec.obs_shape(history))
    if obs.dtype != spec.dtype or tuple(obs.shape) != expected:
        raise ValueError(
            f"td[{spec.obs_key}]: expected {str(spec.dtype).removeprefix('torch.')} {list(expected)}, "
            f"found {_describe(obs)}"
        )
    present = td.get(spec.present_key)
    if present.dtype != torch.bool or tuple(present.shape) != (batch,):
        raise ValueError(f"td[{spec.present_key}]: expected bool [{batch}], found {_describe(present)}")
    bad = nonfinite_rows(obs) & present
    if bool(bad.any()) and nonfinite == "raise":
        raise ValueError(
            f"td[{spec.obs_key}] holds NaN or Inf in {int(bad.sum())} sample(s) where {spec.present_key} is "
            f"True (batch indices {_indices(bad)}); mark those samples absent ({spec.present_key} = False), "
            "or build the model with nonfinite='absent' to read them as absent"
        )
    return bad


def _check_target(td, batch: int, horizon: int | None, target_dim: int | None) -> None:
    if TARGET not in td.keys():
        raise KeyError(f"batch is missing key {TARGET!r} (the future to forecast, [B, T, D])")
    target = td.get(TARGET)
    expected = (
        batch,
        horizon if horizon is not None else target.shape[1],
        target_dim if target_dim is not None else target.shape[-1],
    )
    if not target.is_floating_point() or tuple(target.shape) != expected:
        raise ValueError(f"td[{TARGET!r}]: expected float {list(expected)}, found {_describe(target)}")


def _check_actions(td, batch: int, action_shape: tuple[int, int]) -> None:
    if FUTURE_ACTION not in td.keys():
        raise KeyError(
            f"batch is missing key {FUTURE_ACTION!r}: this model is action-conditioned (a world model) and "
            f"needs the actions applied over the horizon, float32 [B, {action_shape[0]}, {action_shape[1]}] "
            "(set `action` in the data config)"
        )
    action = td.get(FUTURE_ACTION)
    expected = (batch, *action_shape)
    if action.dtype != torch.float32 or tuple(action.shape) != expected:
        raise ValueError(
            f"td[{FUTURE_ACTION!r}]: expected float32 {list(expected)}, found {_describe(action)}"
        )
    bad = nonfinite_rows(action)
    if bool(bad.any()):
        raise ValueError(
            f"td[{FUTURE_ACTION!r}] holds NaN or Inf (batch indices {_indices(bad)}); a forecast "
            "under a non-finite action has no meaning"
        )
