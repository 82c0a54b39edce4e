"""Configuration of the paper's attention-based CVAE forecaster."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import ClassVar, Literal

from mmf_rl.configuration import SavedConfigMixin
from mmf_rl.keys import NONFINITE_RULES, ModalitySpec, NonFiniteRule
from mmf_rl.models.encoders import check_encoder
from mmf_rl.models.fusion import check_fusion
from mmf_rl.objectives.distributions import (
    DEFAULT_OUTPUT_DF,
    DEFAULT_OUTPUT_DISTRIBUTION,
    output_distribution_of,
)

EVAL_LATENTS = ("mean", "sample", "predictive", "posterior")
DECODER_INPUTS = ("tokens", "mixed", "pair_streams", "mixed_pair_streams")
DECODER_LATENTS = ("joint", "linear", "none")
PAIR_SELF = ("always", "alone")
DECODE_FROM = ("zero", "constant_velocity")
POSTERIOR_READS = ("target", "residual")


@dataclass
class ForecasterConfig(SavedConfigMixin):
    """Sizes and choices of :class:`MultimodalForecaster`.

    Args:
        modalities (list[ModalitySpec]): one :class:`ModalitySpec` (or its dict) per input modality, at
            least one; their order fixes the rows of the learned modality embeddings ``P^E`` and ``P^D``.
        history (int, optional): ``H``, past steps per window. Defaults to ``10``.
        horizon (int, optional): ``T``, future steps forecast. Defaults to ``10``.
        target_dim (int, optional): ``D``, dims of the forecast variable. Defaults to ``2``.
        d_model (int, optional): ``d``, the common width of modality tokens. Defaults to ``64``.
        d_latent (int, optional): ``d_z``. Defaults to ``16``.
        num_heads (int, optional): heads of every attention block (``d_model`` must divide by it).
            Defaults to ``4``.
        num_encoder_layers (int, optional): ``L``: ``L - 1`` pre-LN Transformer layers, then the fixed-query
            aggregation layer (the paper uses ``L = 2``, the default).
        mlp_hidden (int, optional): hidden width of the Transformer MLPs and the decoder's shared MLP.
            Defaults to ``128``.
        head_hidden (int, optional): hidden width of the posterior and output heads. Defaults to ``256``.
        min_scale (float, optional): floor added to every predicted scale. Defaults to ``1e-3``.
        prior (str, optional): ``"standard"`` (default, the paper's fixed
            ``N(0, I)``) or ``"learned"``: a conditional prior ``p(z|X)`` computed by a head on the multimodal
            encoder's fused representation of the present modalities, so the fusion shapes every test-time
            forecast (the latent is drawn from it at test time). ``loss_kl`` becomes
            ``KL(q(z|X, y) || p(z|X))``. The default stays ``"standard"`` by measurement (see
            docs/results.md): the learned prior is no more accurate, and its forecast scale, trained on
            posterior draws that know ``y``, is overconfident when decoded at the prior's mean.
        posterior_uses_target (bool, optional): whether the future ``y`` enters the posterior head in training
            (a CVAE's ``q(z|X, y)``). ``None`` (default): ``True`` with the learned prior (which
            needs it: a posterior that sees only ``X`` can copy the prior), ``False`` with the
            standard prior (the paper's literal ``q(z|X)``): with the standard prior, ``True``
            lets ``z`` carry the future that the ``N(0, I)`` draws at test time do not know, so
            forecasts get worse and seed-dependent (see docs/results.md).
        eval_latent (str, optional): the latent(s)
            ``forward`` and :meth:`~MultimodalForecaster.decode_under_actions` decode in eval mode: ``"mean"``
            (default: the prior's mean, a deterministic forecast; ``z = 0`` under the standard prior),
            ``"sample"`` (one draw from the prior, from the global RNG) or ``"predictive"``:
            ``K = predictive_samples`` fixed prior draws ``z_k = μ_p + σ_p ε_k`` decoded in one batched pass,
            and the forecast is the moment-matched Gaussian of their mixture, ``loc = mean_k μ_k``,
            ``scale = sqrt(mean_k σ_k² + var_k μ_k)``: the spread of the prior samples enters the forecast's
            scale: it fixes the learned prior's overconfident scale without retraining
            (``mmf-rl eval ... eval_latent=predictive``). The ``ε_k`` are fixed (seeded, antithetic pairs), so
            the forecast is deterministic and leaves the global RNG alone. ``"posterior"``: the mean of
            ``q(z | X)``, the fusion's posterior (the paper's eqs. 10 and 15 read literally; needs a posterior
            that does not read the target). Cost of ``"predictive"``: every eval decode runs on ``K×`` the
            rows (a planner's ``decode_under_actions`` decodes ``B × N × K`` rows for ``N`` candidates). It
            also applies to a validation loss computed in eval mode. :meth:`MultimodalForecaster.sample`
            always samples, from the global RNG.
        learned_samples (int, optional): ``K`` of a learned sampler (DLow,
            :mod:`mmf_rl.models.latent_sampler`): a network on the fused representation that makes ``K``
            latent codes per history, trained after the forecaster with the forecaster frozen
            (``mmf-rl train sampler.steps=N``); :meth:`MultimodalForecaster.sample` then decodes those codes
            when asked for ``K`` samples. ``0`` (default): no sampler; ``sample`` draws from the prior.
        predictive_samples (int, optional): ``K`` of ``eval_latent="predictive"``: an even number ``>= 2``
            (the ``ε_k`` come in antithetic pairs ``±ε``); unused by the other eval latents. Defaults to
            ``16``.
        fusion (str, optional): the multimodal encoder of the posterior: ``"agnostic"`` (default, the
            paper's modality-agnostic attention) or an ablation of :mod:`mmf_rl.models.fusion`
            (``"linear"``, ``"average"``, ``"sum"``, ``"cross_attention"``).
        decoder_input (str, optional): what the
            decoder reads: ``"mixed"`` (default: the unimodal encoders' tokens after the multimodal encoder's
            self-attention layers, so the fusion acts on every forecast whatever the prior; a fusion without
            such layers passes them through) or ``"tokens"`` (the paper read literally: the raw tokens, and
            under the standard prior the fusion shapes only training). A saved model's config without it
            loads as ``"tokens"`` (:meth:`from_saved_dict`). ``"pair_streams"`` (MulT's streams): for each
            ordered pair ``(i, j)`` of modalities, a cross-modal layer of its own lets ``i``'s last present
            token attend to ``j``'s present tokens; the decoder reads the ``M × M`` readouts (absent when
            ``i`` or ``j`` is), each with ``p^D_i`` (:class:`~mmf_rl.models.attention.PairStreams`).
            ``"mixed_pair_streams"``: the same streams over the mixed tokens, so the fusion acts on every
            forecast.
        pair_self (str, optional): the self pairs ``i <- i`` of the pair streams:
            ``"always"`` read (default) or only when ``i`` is the only present modality (``"alone"``: with two
            or more, the decoder reads MulT's ``M (M - 1)`` cross pairs alone; the self-pair layers then learn
            only from windows with one modality left, which ``L_mis`` dropping one of three never makes).
            Unused without pair streams.
        decoder_latent (str, optional): how ``z`` (and a world model's actions)
            enter the decoder's tokens ``H0``: ``"joint"`` (default, the paper: the shared MLP over
            ``[x̄ + p^D, z (, a)]``), ``"linear"`` (``H0 = x̄ + p^D + W [z (, a)]``: no MLP over every token)
            or ``"none"`` (a deterministic decoder that ignores ``z``; the actions still enter, linearly). A
            saved model's config without it loads as ``"joint"``, the default.
        action_dim (int, optional): ``A``; with ``action_steps``, makes the model an action-conditioned world
            model that reads ``"future_action"`` ``[B, action_steps, A]`` (the actions applied
            over the horizon). ``0`` (default): no action input, the paper's forecaster.
        action_steps (int, optional): ``S``, frames of actions over the horizon (``T × stride`` in the data).
        nonfinite (str, optional): NaN/Inf under a present modality of an input batch: ``"raise"``
            (default; the error names the key and the samples) or ``"absent"`` (those samples' modality is
            read as absent). See :func:`mmf_rl.keys.validate_batch`.
        output_distribution (str, optional): the family the forecast's ``(loc, scale)`` is read with, by
            the losses, the evaluation and the scale calibration: ``"normal"`` (default, ``N(loc,
            scale²)``), ``"laplace"`` or ``"student_t"`` (heavier tails;
            :mod:`mmf_rl.objectives.distributions`). The decoder is the same; a saved model's config without
            it loads as ``"normal"``.
        output_df (float, optional): the degrees of freedom of ``"student_t"`` (``> 2``; unused by the other
            families). Defaults to ``4``.
        decode_from (str, optional): what the decoder's ``loc`` is an offset from: ``"zero"`` (default,
            the paper: the decoder predicts the future itself) or ``"constant_velocity"``: the forecast's
            ``loc``, and every decoded mean (prior and learned-sampler samples, the ``"predictive"``
            mixture, the L_mis and GSNN decodes), is the decoder's output plus the constant-velocity
            extrapolation of the target's own past (``"target_past"``: the data config needs
            ``include_target_past: true``, which ETH/UCY's and ``mmf-rl inspect``'s configs set). The
            decoder then learns corrections to constant velocity, and a decoder whose output is near
            zero forecasts constant velocity (Schöller et al. 2020). The scale is the decoder's, unchanged.
            Use it for trajectories (pedestrians, vehicles) where constant velocity is a strong
            reference the plain decoder does not reach; it needs ``history >= 2``, and a world model
            (``action_dim > 0``) refuses it. A saved model's config without it loads as ``"zero"``.
        posterior_reads (str, optional): what a posterior ``q(z|X, y)`` reads of the future ``y``:
            ``"residual"`` (default), ``y`` minus what the decodes add to the decoder's output (its offset
            from constant velocity with ``decode_from="constant_velocity"``; ``y`` itself with ``"zero"``),
            so that ``z`` encodes what the decoder must produce; or ``"target"``, ``y`` itself (ETH/UCY
            runs with constant velocity that read ``y`` had a silent latent, KL 0.07 nats, and their
            samples collapsed onto the point forecast). Unused by a posterior that does not read ``y``.
            A saved model's config without it loads as ``"target"``, what it was trained with.

    Raises:
        ValueError: no modality or duplicate names, an unknown encoder or fusion, a size below 1,
            ``d_model`` not divisible by ``num_heads``, ``min_scale <= 0``, an option outside its choices,
            ``predictive_samples`` odd or below 2, ``action_dim`` and ``action_steps`` not both set or both
            0, ``decode_from="constant_velocity"`` with ``history < 2`` or a world model, an unknown
            ``output_distribution``, ``output_df <= 2`` with ``"student_t"``, or a latent setup that cannot
            work (``prior="learned"`` with ``posterior_uses_target=False``,
            ``eval_latent="posterior"`` with a posterior that reads the target); the message names the field.

    Examples:
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig
        >>> camera = ModalitySpec("camera", "image", (3, 32, 32))
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> config = ForecasterConfig(
        ...     modalities=[camera, force],
        ...     history=8,
        ...     horizon=10,
        ...     prior="learned",
        ... )
        >>> config.modality_names, config.posterior_reads_target
        (['camera', 'force'], True)
        >>> ForecasterConfig.from_dict(config.to_dict()) == config
        True
        >>> fresh = ForecasterConfig.from_dict({"modalities": [force]})  # today's defaults
        >>> saved_before = {k: v for k, v in fresh.to_dict().items() if k != "decoder_input"}
        >>> fresh.decoder_input, ForecasterConfig.from_saved_dict(saved_before).decoder_input
        ('mixed', 'tokens')
        >>> ForecasterConfig(modalities=config.modalities, d_model=30, num_heads=4)
        Traceback (most recent call last):
            ...
        ValueError: ForecasterConfig: d_model=30 must be divisible by num_heads=4
    """

    modalities: list[ModalitySpec] = field(default_factory=list)
    history: int = 10
    horizon: int = 10
    target_dim: int = 2
    d_model: int = 64
    d_latent: int = 16
    num_heads: int = 4
    num_encoder_layers: int = 2
    mlp_hidden: int = 128
    head_hidden: int = 256
    min_scale: float = 1e-3
    prior: Literal["standard", "learned"] = "standard"
    posterior_uses_target: bool | None = None
    eval_latent: Literal["mean", "sample", "predictive", "posterior"] = "mean"
    learned_samples: int = 0
    predictive_samples: int = 16
    fusion: str = "agnostic"
    decoder_input: Literal["tokens", "mixed", "pair_streams", "mixed_pair_streams"] = "mixed"
    decoder_latent: Literal["joint", "linear", "none"] = "joint"
    pair_self: Literal["always", "alone"] = "always"
    action_dim: int = 0
    action_steps: int = 0
    nonfinite: NonFiniteRule = "raise"
    output_distribution: str = DEFAULT_OUTPUT_DISTRIBUTION
    output_df: float = DEFAULT_OUTPUT_DF
    decode_from: Literal["zero", "constant_velocity"] = "zero"
    posterior_reads: Literal["target", "residual"] = "residual"
    # The settings a config saved without them reads at the value that config described (to_dict
    # writes every setting: a saved config lacks one only if older), whose default changed since
    # (decoder_input, posterior_reads) or may change (output_distribution).
    SAVED_BEFORE: ClassVar[dict[str, object]] = {
        "decoder_input": "tokens",
        "output_distribution": "normal",
        "decode_from": "zero",
        "posterior_reads": "target",
    }

    def __post_init__(self):
        self.modalities = [
            m if isinstance(m, ModalitySpec) else ModalitySpec.from_dict(m) for m in self.modalities
        ]
        self._check_modalities()
        self._check_sizes()
        self._check_latent()
        self._check_options()

    def _check_modalities(self) -> None:
        if not self.modalities:
            raise ValueError(
                "ForecasterConfig.modalities is empty: the forecaster needs at least one modality"
            )
        names = [m.name for m in self.modalities]
        if len(set(names)) != len(names):
            raise ValueError(f"ForecasterConfig.modalities: duplicate names in {names}")
        for spec in self.modalities:
            check_encoder(spec.name, spec.encoder, spec.kind)

    def _check_sizes(self) -> None:
        for name in (
            "history",
            "horizon",
            "target_dim",
            "d_model",
            "d_latent",
            "num_heads",
            "num_encoder_layers",
            "mlp_hidden",
            "head_hidden",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"ForecasterConfig.{name} must be an integer >= 1, found {value!r}")
        if not self.min_scale > 0:
            raise ValueError(
                f"ForecasterConfig.min_scale must be > 0 (the floor of every forecast scale), found "
                f"{self.min_scale!r}"
            )
        if self.d_model % self.num_heads:
            raise ValueError(
                f"ForecasterConfig: d_model={self.d_model} must be divisible by num_heads={self.num_heads}"
            )

    def _check_latent(self) -> None:
        """The prior, posterior and eval latent must fit together."""
        if self.prior not in ("standard", "learned"):
            raise ValueError(f"ForecasterConfig.prior must be 'standard' or 'learned', found {self.prior!r}")
        if self.prior == "learned" and self.posterior_uses_target is False:
            raise ValueError(
                "ForecasterConfig: prior='learned' needs the posterior q(z|X, y) to read the target "
                "(a posterior of X alone can copy the prior); set posterior_uses_target to null or true"
            )
        if self.eval_latent not in EVAL_LATENTS:
            raise ValueError(
                f"ForecasterConfig.eval_latent must be one of {EVAL_LATENTS}, found {self.eval_latent!r}"
            )
        if self.eval_latent == "posterior" and self.posterior_reads_target:
            raise ValueError(
                "ForecasterConfig: eval_latent='posterior' decodes at the mean of q(z|X), which a posterior "
                "that reads the target cannot give at test time; set posterior_uses_target=false (and "
                "prior=standard) or choose another eval_latent"
            )
        if (
            isinstance(self.learned_samples, bool)
            or not isinstance(self.learned_samples, int)
            or (self.learned_samples < 0)
        ):
            raise ValueError(
                "ForecasterConfig.learned_samples must be a whole number >= 0 (0: no learned sampler), "
                f"found {self.learned_samples!r}"
            )
        if (
            not isinstance(self.predictive_samples, int)
            or self.predictive_samples < 2
            or self.predictive_samples % 2
        ):
            raise ValueError(
                "ForecasterConfig.predictive_samples must be an even integer >= 2 (the latents of "
                f"eval_latent='predictive' come in antithetic pairs), found {self.predictive_samples!r}"
            )

    def _check_options(self) -> None:
        if self.action_dim < 0 or self.action_steps < 0 or (self.action_dim > 0) != (self.action_steps > 0):
            raise ValueError(
                f"ForecasterConfig: action_dim={self.action_dim} and action_steps={self.action_steps} must "
                "both be > 0 (an action-conditioned world model) or both 0 (no action input)"
            )
        if self.nonfinite not in NONFINITE_RULES:
            raise ValueError(
                f"ForecasterConfig.nonfinite must be one of {NONFINITE_RULES}, found {self.nonfinite!r}"
            )
        check_fusion(self.fusion)
        try:
            output_distribution_of(self)
        except ValueError as error:
            raise ValueError(f"ForecasterConfig: {error}") from None
        options = {
            "decoder_input": DECODER_INPUTS,
            "decoder_latent": DECODER_LATENTS,
            "pair_self": PAIR_SELF,
            "decode_from": DECODE_FROM,
            "posterior_reads": POSTERIOR_READS,
        }
        for name, allowed in options.items():
            if (value := getattr(self, name)) not in allowed:
                raise ValueError(f"ForecasterConfig.{name} must be one of {allowed}, found {value!r}")
        if self.decode_from == "constant_velocity" and self.history < 2:
            raise ValueError(
                f"ForecasterConfig: decode_from='constant_velocity' extrapolates the last step of the "
                f"target's past, which needs history >= 2, found history={self.history}"
            )
        if self.decode_from == "constant_velocity" and self.action_dim:
            raise ValueError(
                "ForecasterConfig: decode_from='constant_velocity' is not supported by a world model "
                "(action_dim > 0): its forecasts under candidate actions (decode_under_actions) read no "
                "target past; set decode_from=zero"
            )

    @property
    def modality_names(self) -> list[str]:
        """The modalities' names, in order."""
        return [m.name for m in self.modalities]

    @property
    def posterior_reads_target(self) -> bool:
        """Whether the posterior is ``q(z|X, y)`` (see ``posterior_uses_target``)."""
        return self.prior == "learned" if self.posterior_uses_target is None else self.posterior_uses_target

    @property
    def action_shape(self) -> tuple[int, int] | None:
        """``(S, A)`` of ``"future_action"`` for a world model, else ``None``."""
        return (self.action_steps, self.action_dim) if self.action_dim else None

    def to_dict(self) -> dict:
        """The config as plain data (modalities as dicts), what :meth:`from_dict` reads back."""
        d = asdict(self)
        d["modalities"] = [m.to_dict() for m in self.modalities]
        return d
