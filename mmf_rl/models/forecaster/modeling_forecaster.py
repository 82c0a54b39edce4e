"""The paper's attention-based CVAE forecaster as a ``TensorDictModule``.

Pipeline for a batch ``[B]`` with ``M`` modalities (paper, "Model Architecture"):

1. **Unimodal encoders** ``E_m`` turn each present window into tokens: one ``x̄_m ∈ R^d`` (the
   paper), or one per step (``steps``, ``conv_frames`` encoders: the detail step-wise models such
   as MulT keep). Each encoder runs once, on the rows where its modality is present (gathered);
   absent rows get zero tokens. So the value stored under an absent modality never reaches any
   computation, and an encoder whose modality is absent from the whole batch does not run and gets
   no gradient.
2. **Multimodal encoder** (posterior, and the learned prior): ``+ p^E_m`` on every token of ``m``,
   ``L - 1`` pre-LN Transformer layers, then modality-agnostic attention with the fixed queries
   ``P^E`` (always ``M`` rows, however many tokens), flatten, MLP -> ``(μ, σ)`` of ``q(z | X)``;
   with ``prior="learned"`` a second MLP on the same fused representation -> ``(μ, σ)`` of
   ``p(z | X)``. Absent tokens are masked out of every attention (``key_padding_mask``): one pass
   for any mix of presence patterns. Any registered fusion (:mod:`mmf_rl.models.fusion`) can take
   its place, and the decoder's aggregation's with it.
3. **Decoder**: ``[(x̄_m + p^D_m) ⊕ z]`` per token -> shared MLP -> ``H0``; ``H1 = MHA(LN(P^D),
   LN(H0), LN(H0)) + P^D``; ``H2 = MHA(LN(H1), LN(H0), LN(H0)) + H1``; flatten, MLP -> ``loc``,
   ``scale`` of the output distribution over the ``T × D`` future (a diagonal Gaussian by default;
   ``output_distribution`` says how they are read), in the normalised frame of the target. With
   ``decoder_input="mixed"`` its tokens are those after the multimodal encoder's Transformer layers,
   so the fusion shapes every forecast; with ``"pair_streams"``, MulT's ``M × M`` pair readouts
   (:class:`~mmf_rl.models.attention.PairStreams`), each with ``p^D`` of its query modality.
   ``decoder_latent`` chooses how ``z`` enters ``H0``: the shared MLP (the paper), a linear map
   added to each token, or not at all.

Open points of the paper, and what this implementation does:

* **Residual after the fixed-query attention.** The paper adds the block's input (``M^(i)``
  rows) to an output of ``M`` rows. We add the queries (``P^E`` in the encoder, ``P^D`` for
  ``H1``), as the Set Transformer's pooling block does; ``H2``'s residual is ``H1`` (same rows).
  Adding the padded input instead would leak which modalities are present into fixed rows.
* **Concatenation size.** ``(x̄_m + p^D_m) ⊕ z`` has ``d + d_z`` features (the paper's
  ``d × d_z`` is a typo for concatenation); the shared MLP maps it back to ``d``.
* **How ``y`` reaches the posterior.** The paper writes ``q(z|X)`` but trains "with the target
  ``y`` as input". By default we follow the equations: ``q(z|X)``. With
  ``posterior_uses_target=True``, ``y`` (flattened ``T × D``) goes through an MLP to a
  ``d``-vector concatenated to the flattened modality-agnostic output before the posterior head
  (a CVAE's ``q(z|X, y)``; ``ForecasterConfig`` says why it is not the default). That ``y`` is what
  the decoder must produce (:meth:`MultimodalForecaster.posterior_future`): with
  ``decode_from="constant_velocity"``, its offset from the extrapolation (``posterior_reads="residual"``,
  the default; ``"target"``, the raw ``y``, is how models saved before the setting load).
* **Inference.** ``z`` from the prior: ``forward`` in eval mode uses the prior's mean by
  default (deterministic forecasts for RL and metrics); :meth:`sample` draws ``K`` latents for
  best-of-K. ``eval_latent="predictive"`` decodes ``K`` fixed prior draws in one batched pass
  and writes the moment-matched Gaussian of their mixture (mean of the means; variance = mean
  variance + variance of the means; for another output family, its member with these moments): the
  forecast's scale then carries the spread of ``p(z|X)``, which the decoder's own scale, trained on
  posterior draws that know ``y``, misses (a learned prior decoded at its mean is overconfident). No
  retraining: ``mmf-rl eval`` can apply it to any checkpoint. With the paper's standard prior
  ``N(0, I)`` (``prior="standard"``) the multimodal encoder feeds only the posterior, so a forecast
  decoded from the prior does not depend on it:
  it shapes the model through training alone (see docs/results.md). The paper's eq. (15)
  integrates over ``p(z | X)`` and says the prior can be learned: ``prior="learned"`` is that
  conditional prior, a head on the fused representation of the present modalities, so the
  fusion acts on every test-time forecast. Its posterior reads the target (``q(z | X, y)``)
  and ``loss_kl = KL(q(z | X, y) || p(z | X))``.
* **World model (action conditioning, not in the paper).** With ``action_dim > 0`` the model
  forecasts the future *under a given action sequence*: ``"future_action"`` ``[B, S, A]``
  (``S = T × stride`` actions, from the last observed frame on) is flattened and mapped by an
  MLP to one ``d``-vector ``a``, concatenated beside ``z`` to every decoder token:
  ``[(x̄_m + p^D_m) ⊕ z ⊕ a]`` (with ``decoder_latent="linear"`` or ``"none"``, added through the
  linear map with ``z`` or alone). The actions enter the decoder only: the posterior still
  summarises the observed history, so the presence handling (masks, ``L_mis``) is unchanged,
  and a planner scores ``N`` candidate sequences for one history by encoding it once and
  decoding ``N`` rows (:meth:`MultimodalForecaster.forecast_under_actions`). One vector for the
  whole sequence, not per-step tokens: with ``T`` of about 10 the MLP sees every action at every
  output step, and the decoder's cost stays that of ``M`` tokens.
* **Missing-modality decode.** If the batch carries ``("drop", m)`` masks, the same ``z`` and
  tokens are decoded twice, with and without the dropped modalities, in **one** batched pass
  of ``2B`` rows (used by :class:`~mmf_rl.objectives.MissingModalityLoss`). With the learned
  prior the multimodal encoder also runs on both presence patterns in one pass of ``2B`` rows
  and writes the prior of the degraded input, ``("prior_dropped", ...)``, which the loss ties
  to the full-input prior. ``("drop_steps", m)`` masks ``[B, H]`` (a tail cut: a sensor dying
  mid-window) make those steps absent for the student only: the cut modality is encoded again on
  the cut rows as if the steps were absent in ``("present_steps", m)``, the teacher's tokens
  unchanged.
* **GSNN term (Sohn et al. 2015).** If the batch carries ``"decode_from_prior"`` (set by
  :class:`~mmf_rl.objectives.ELBOLoss` with ``gsnn_weight > 0``), every row is also decoded
  from a reparameterised ``z ~ p(z | X)`` in the same decoder pass, written to
  ``("forecast_from_prior", ...)``: training then also sees the latents used at test time.
* **Best-of-K term (Bhattacharyya et al. 2018).** If the batch carries ``"decode_prior_draws"``
  ``[B, K]`` (set by :class:`~mmf_rl.objectives.ELBOLoss` with ``best_of_k_weight > 0``), every
  row is also decoded from ``K`` reparameterised draws ``z ~ p(z | X)`` in the same decoder pass,
  their means written to ``("forecast_from_prior", "samples")`` ``[B, K, T, D]``, unmixed: the loss
  scores the best one.
* **Learned sampler (DLow, Yuan & Kitani 2020; not in the paper).** With ``learned_samples = K`` a
  small network on the fused representation makes ``K`` latent codes per history
  (:mod:`mmf_rl.models.latent_sampler`), trained after the forecaster with the forecaster frozen
  (:class:`~mmf_rl.objectives.DiverseSamplingLoss`); :meth:`MultimodalForecaster.sample` decodes them
  when asked for ``K`` samples. Independent prior draws cover the futures unevenly, which best-of-``K``
  metrics punish; the point forecast is unchanged.
* **Decoding from constant velocity (not in the paper).** With ``decode_from="constant_velocity"``
  every decoded mean is the decoder's output plus the constant-velocity extrapolation of
  ``"target_past"`` (in the normalised target frame, which is the normalised extrapolation in the
  target's units: :func:`~mmf_rl.models.baselines.constant_velocity.constant_velocity`): the decoder
  learns corrections to constant velocity. The shift is common to the ``K`` decodes of a row, so the
  moment-matched scale is unchanged. A posterior that reads ``y`` reads its offset from the
  extrapolation, what the decoder produces (reading ``y`` itself, the latent fell silent on ETH/UCY).
  :meth:`MultimodalForecaster.decode` stays the decoder's own output (the offset);
  :meth:`MultimodalForecaster.forecast_from_tokens`, which reads no target past, refuses such a model.
"""

from __future__ import annotations

import contextlib
import dataclasses

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from mmf_rl import keys
from mmf_rl.models.attention import FixedQueryAttention, PairStreams
from mmf_rl.models.baselines.constant_velocity import constant_velocity, target_past_of
from mmf_rl.models.encoders import build_encoder, mlp, num_tokens
from mmf_rl.models.forecaster.configuration_forecaster import ForecasterConfig
from mmf_rl.models.fusion import FusionShape, build_fusion
from mmf_rl.models.hub import PretrainedModel
from mmf_rl.models.latent_sampler import LatentSampler
from mmf_rl.models.registry import register_model
from mmf_rl.models.rows import compute_on_rows
from mmf_rl.models.scale_calibration import PresenceScaleCalibration
from mmf_rl.objectives.distributions import output_distribution_of


def antithetic_normal(num: int, dim: int) -> torch.Tensor:
    """``num`` (even) fixed standard-normal vectors ``[num, dim]``: ``num / 2`` seeded draws ``ε``,
    then ``-ε``.

    Fixed (a private seeded generator): a predictive forecast is reproducible and leaves the global
    RNG alone. Antithetic: the ``ε`` average exactly to 0, so for any ``K`` the mixture's mean is
    exact for a decoder linear in ``z`` and otherwise centred on the prior-mean decode to first
    order, the Monte Carlo error left to the curvature only.
    """
    half = torch.randn(num // 2, dim, generator=torch.Generator().manual_seed(0))
    return torch.cat([half, -half])


def moment_match(
    loc: torch.Tensor, scale: torch.Tensor, draws: int, variance: float = 1.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """The member of the output family with the mean and variance of the equal-weight mixture of
    ``draws`` members (the Gaussian of a Gaussian mixture).

    ``loc``, ``scale`` ``[draws × N, ...]`` (row ``k * N + n`` is component ``k`` of ``n``) ->
    ``[N, ...]``: ``mean_k μ_k`` and ``sqrt(mean_k σ_k² + var_k μ_k / v)`` (population variance), ``v``
    the ``variance`` of the family's standard member (1 for the Gaussian; a member of scale ``σ`` has
    variance ``v σ²``)."""
    if draws == 1:
        return loc, scale
    loc, scale = loc.unflatten(0, (draws, -1)), scale.unflatten(0, (draws, -1))
    # Dividing by 1.0 is exact: the Gaussian's moment matching is what it was.
    scale_variance = scale.square().mean(0) + loc.var(0, correction=0) / variance
    return loc.mean(0), scale_variance.sqrt()


def latent_gaussian(raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A latent head's output ``[N, 2 d_z]`` -> ``loc``, ``scale`` ``[N, d_z]``: softplus plus a small
    floor, so that no scale reaches 0 and the KL terms stay finite."""
    loc, raw_scale = raw.chunk(2, dim=-1)
    return loc, F.softplus(raw_scale) + 1e-4


class ModalitySpecificDecoder(nn.Module):
    """The paper's decoder: tokens, presence and ``z`` -> Gaussian parameters over ``T × D``."""

    def __init__(self, cfg: ForecasterConfig, fusion_shape: FusionShape):
        super().__init__()
        m, d = len(cfg.modalities), cfg.d_model
        self.modality_embedding = nn.Parameter(torch.randn(m, d) * 0.02)  # P^D
        self.latent = cfg.decoder_latent
        conditions = (0 if self.latent == "none" else cfg.d_latent) + (d if cfg.action_dim else 0)
        if self.latent == "joint":
            self.joint = mlp(d + conditions, cfg.mlp_hidden, d)
        else:  # "linear", or "none" (then only a world model's actions enter)
            self.condition = nn.Linear(conditions, d) if conditions else None
        # The aggregation: the paper's two attentions from P^D, or the ablation fusion that replaces them.
        self.fusion = build_fusion(cfg.fusion, fusion_shape)
        if self.fusion is None:
            self.aggregate = FixedQueryAttention(d, cfg.num_heads)
            self.refine = FixedQueryAttention(d, cfg.num_heads)
        self.head = mlp(m * d, cfg.head_hidden, 2 * cfg.horizon * cfg.target_dim)
        self.out_shape = (cfg.horizon, cfg.target_dim)
        self.min_scale = cfg.min_scale

    def joint_tokens(
        self, tokens: torch.Tensor, token_modality: torch.Tensor, z: torch.Tensor, action: torch.Tensor | None
    ) -> torch.Tensor:
        """``H0``: every token with ``p^D`` of its modality, and ``z`` (and the actions) by
        ``decoder_latent``: through the shared MLP (``"joint"``) or added by a linear map."""
        x = tokens + self.modality_embedding[token_modality]
        conditions = [c for c in (None if self.latent == "none" else z, action) if c is not None]
        if not conditions:
            return x
        conditions = torch.cat(conditions, dim=-1)
        if self.latent == "joint":
            return self.joint(torch.cat([x, conditions.unsqueeze(1).expand(*x.shape[:2], -1)], dim=-1))
        return x + self.condition(conditions).unsqueeze(1)

    def forward(
        self,
        tokens: torch.Tensor,
        absent: torch.Tensor,
        token_modality: torch.Tensor,
        z: torch.Tensor,
        action: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        n = tokens.shape[0]
        h0 = self.joint_tokens(tokens, token_modality, z, action)
        if self.fusion is None:
            queries = self.modality_embedding.expand(n, -1, -1)
            h1 = self.aggregate(queries, h0, absent, residual=queries)
            h2 = self.refine(h1, h0, absent, residual=h1)
        else:
            h2 = self.fusion(h0, absent, token_modality)
        loc, raw_scale = self.head(h2.flatten(1)).view(n, 2, *self.out_shape).unbind(1)
        return loc, F.softplus(raw_scale) + self.min_scale


# The paper's losses: its ELBO and the missing-modality loss (off at loss.missing_modality_weight=0).
@register_model("forecaster", ForecasterConfig, loss=("elbo", "mis"))
class MultimodalForecaster(TensorDictModuleBase, PretrainedModel):
    """Attention-based CVAE forecaster robust to missing modalities (see module docstring).

    Reads ``("obs", m)``, ``("present", m)`` for every modality, ``"target"`` when training
    (and, if present, in eval, to report the posterior), optional ``("present_steps", m)``,
    ``("drop", m)``, ``("drop_steps", m)``, ``"decode_from_prior"`` and ``"decode_prior_draws"``, and
    ``"target_past"`` with ``decode_from="constant_velocity"``; writes ``("forecast", "loc"/"scale")``,
    ``"latent"``, ``("prior", ...)``, ``("posterior", ...)`` (when ``"target"`` is given or not needed),
    ``("forecast_dropped", ...)`` and, with the learned prior, ``("prior_dropped", ...)`` (when
    ``("drop", m)`` is given), and ``("forecast_from_prior", ...)`` (when requested).

    In train mode ``z`` is sampled from the posterior (reparameterised); in eval mode it is the
    prior's mean (``eval_latent="mean"``; ``0`` under the standard prior), a prior draw
    (``"sample"``), or ``K`` fixed prior draws whose decodes are moment-matched into one Gaussian
    (``"predictive"``; ``"latent"`` is then the prior's mean). In eval mode the eval forecast's
    scale (``forward``, :meth:`forecast_from_tokens`, :meth:`decode_under_actions`) is multiplied
    by its presence pattern's factor (``scale_calibration``: ones until ``mmf-rl calibrate`` fits
    them; see :mod:`mmf_rl.models.scale_calibration`).

    Args:
        config (ForecasterConfig): the sizes and choices.

    Examples:
        A forecaster of two modalities, on a batch where the third sample lost its force sensor:

        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> config = ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... )
        >>> model = MultimodalForecaster(config).eval()
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(3, 4, 6),
        ...     ("present", "force"): torch.tensor([True, True, False]),
        ...     ("obs", "pose"): torch.randn(3, 3),
        ...     ("present", "pose"): torch.ones(3, dtype=torch.bool),
        ... }, batch_size=[3])
        >>> out = model(batch)  # written into `batch`
        >>> out["forecast", "loc"].shape, out["forecast", "scale"].shape  # [B, T, D]
        (torch.Size([3, 5, 2]), torch.Size([3, 5, 2]))
        >>> batch["obs", "force"][2] = float("nan")  # the value under an absent modality is never read
        >>> torch.equal(model(batch.clone())["forecast", "loc"], out["forecast", "loc"])
        True
        >>> model.sample(batch, num_samples=4)["forecast", "samples"].shape  # best-of-K draws
        torch.Size([3, 4, 5, 2])
    """

    def __init__(self, config: ForecasterConfig):
        super().__init__()
        self.config = config
        self.modalities = list(config.modalities)
        # The variance of the output family's standard member: eval_latent="predictive" moment-matches
        # in its units.
        self.output_variance = output_distribution_of(config).variance
        d = config.d_model
        self.encoders = nn.ModuleDict({s.name: build_encoder(s, config.history, d) for s in self.modalities})
        # Keep this order: parameters draw their initial values in creation order, so a reorder changes
        # a seed's initial weights.
        encoder_shape = self._register_token_layout()
        self._build_latent_heads(encoder_shape)
        self._build_decoder(encoder_shape)
        self._build_latent_sampler()
        # The ε_k of eval_latent="predictive". Not persistent: checkpoints stay as they were, and a
        # model saved before the option existed loads unchanged.
        self.register_buffer(
            "predictive_noise",
            antithetic_normal(config.predictive_samples, config.d_latent),
            persistent=False,
        )
        self._declare_keys()

    def _register_token_layout(self) -> FusionShape:
        """``token_counts`` and the modality of each token of :meth:`encode`'s ``[B, N, d]`` (an encoder
        may emit several); returns the shape the multimodal encoder's fusion is built for."""
        self.token_counts = [num_tokens(self.encoders[s.name]) for s in self.modalities]
        self.register_buffer(
            "token_modality",
            torch.repeat_interleave(torch.arange(len(self.modalities)), torch.tensor(self.token_counts)),
            persistent=False,
        )
        # [N, M]: built once, not per call (one_hot reads its input's range, a host sync).
        self.register_buffer(
            "token_modality_one_hot",
            F.one_hot(self.token_modality, len(self.modalities)).bool(),
            persistent=False,
        )
        return FusionShape(
            num_modalities=len(self.modalities),
            num_tokens=sum(self.token_counts),
            d_model=self.config.d_model,
            num_heads=self.config.num_heads,
            mlp_hidden=self.config.mlp_hidden,
            num_layers=self.config.num_encoder_layers,
            role="encoder",
        )

    def _build_latent_heads(self, encoder_shape: FusionShape) -> None:
        """The multimodal encoder's fusion, the posterior head (with the target's encoder when it reads
        ``y``) and, with ``prior="learned"``, the prior head."""
        config, d = self.config, self.config.d_model
        self.fusion = build_fusion(config.fusion, encoder_shape)
        target_numel = config.horizon * config.target_dim
        reads_target = config.posterior_reads_target
        self.target_encoder = mlp(target_numel, config.head_hidden, d) if reads_target else None
        fused = self.fusion.out_rows * d
        self.posterior_head = mlp(fused + (d if reads_target else 0), config.head_hidden, 2 * config.d_latent)
        self.prior_head = (
            mlp(fused, config.head_hidden, 2 * config.d_latent) if config.prior == "learned" else None
        )

    def _build_decoder(self, encoder_shape: FusionShape) -> None:
        """The decoder (after the pair streams it reads with ``decoder_input="pair_streams"`` or
        ``"mixed_pair_streams"``: its ``M × M`` tokens), the scale factors and a world model's action
        encoder."""
        config = self.config
        self.pair_streams = (
            PairStreams(
                self.token_counts, config.d_model, config.num_heads, config.mlp_hidden, config.pair_self
            )
            if config.decoder_input.endswith("pair_streams")
            else None
        )
        tokens = encoder_shape.num_tokens if self.pair_streams is None else len(self.pair_streams.pairs)
        decoder_shape = dataclasses.replace(encoder_shape, role="decoder", num_tokens=tokens)
        self.decoder = ModalitySpecificDecoder(config, decoder_shape)
        self.scale_calibration = PresenceScaleCalibration(len(self.modalities), config.horizon)
        self.action_encoder = (
            mlp(config.action_steps * config.action_dim, config.head_hidden, config.d_model)
            if config.action_dim
            else None
        )

    def _build_latent_sampler(self) -> None:
        """The learned sampler (``learned_samples > 0``), its weights drawn from a forked RNG: a forecaster
        built with one starts from the weights and random draws of one built without."""
        config = self.config
        self.latent_sampler = None
        if config.learned_samples:
            with torch.random.fork_rng(devices=[]):
                self.latent_sampler = LatentSampler(
                    self.fusion.out_rows * config.d_model, config.d_latent, config.learned_samples
                )

    def _declare_keys(self) -> None:
        """``in_keys`` and ``out_keys``: the batch contract's inputs and everything forward writes."""
        self.in_keys = [s.obs_key for s in self.modalities] + [s.present_key for s in self.modalities]
        if self.config.action_dim:
            self.in_keys.append(keys.FUTURE_ACTION)
        if self.config.decode_from == "constant_velocity":
            self.in_keys.append(keys.TARGET_PAST)
        self.out_keys = [
            keys.FORECAST_LOC,
            keys.FORECAST_SCALE,
            keys.LATENT,
            keys.PRIOR_LOC,
            keys.PRIOR_SCALE,
            keys.POSTERIOR_LOC,
            keys.POSTERIOR_SCALE,
            keys.FORECAST_DROPPED_LOC,
            keys.FORECAST_DROPPED_SCALE,
            keys.FORECAST_FROM_PRIOR_LOC,
            keys.FORECAST_FROM_PRIOR_SCALE,
            keys.FORECAST_FROM_PRIOR_SAMPLES,
        ]
        if self.prior_head is not None:
            self.out_keys += [keys.PRIOR_DROPPED_LOC, keys.PRIOR_DROPPED_SCALE]

    def explain_state_mismatch(self, state: dict[str, torch.Tensor]) -> str | None:
        """Ablation weights saved when an ablation fusion replaced only the posterior's fusion (the
        decoder kept the paper's attention, ``decoder.aggregate``/``decoder.refine``) do not fit a
        model whose decoder aggregates with the ablation too: refused, naming the fix."""
        if self.decoder.fusion is None or not any(key.startswith("decoder.aggregate.") for key in state):
            return None
        return (
            f"these are weights of the fusion={self.config.fusion!r} ablation saved when an ablation "
            "replaced only the posterior's fusion; the decoder now aggregates with the same fusion, so "
            f"retrain with model.fusion={self.config.fusion}"
        )

    # -- building blocks -------------------------------------------------------------------------

    def validate(self, td: TensorDictBase, require_target: bool = False) -> None:
        """Raise a clear error if ``td`` does not follow the key contract for this model; with
        ``nonfinite="absent"``, mark its present samples holding NaN/Inf absent in ``td``."""
        keys.validate_batch(
            td,
            self.modalities,
            self.config.history,
            self.config.horizon,
            self.config.target_dim,
            require_target=require_target,
            action_shape=self.config.action_shape,
            nonfinite=self.config.nonfinite,
        )
        if self.config.nonfinite == "absent":
            keys.mark_nonfinite_absent(td, self.modalities)
        if self.config.decode_from == "constant_velocity":
            self._target_past(td)  # checked before any encoding; extrapolated where decoded

    def decode_origin(self, td: TensorDictBase) -> torch.Tensor | None:
        """What every decoded mean of ``td``'s windows is an offset from: ``None`` with
        ``decode_from="zero"``; with ``"constant_velocity"``, the constant-velocity extrapolation
        ``[B, T, D]`` of ``td``'s ``"target_past"`` (a ``KeyError`` naming ``include_target_past`` when
        the batch lacks it)."""
        if self.config.decode_from == "zero":
            return None
        return constant_velocity(self._target_past(td), self.config.horizon)

    def _target_past(self, td: TensorDictBase) -> torch.Tensor:
        return target_past_of(td, "decode_from='constant_velocity'", self.config.target_dim)

    def encode(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """Unimodal encoders -> tokens ``[B, N, d]`` (zeros where absent; ``N`` is the sum of the
        encoders' token counts, in modality order) and token presence ``[B, N]``.

        With ``("present_steps", m)`` in ``td``, the absent steps of a present window are zeroed before
        the encoder reads them; a step-token encoder's token of an absent step is also absent (a
        key-padding mask for the fusion and the decoder). Without it every step of a present modality
        is present.

        Args:
            td (TensorDictBase): a batch following `mmf_rl.keys`.

        Returns:
            ``(tokens, presence)``.
        """
        columns = [
            self._encode_modality(
                i,
                td.get(spec.obs_key),
                td.get(spec.present_key),
                td.get(keys.present_steps_key(spec.name), None),
            )
            for i, spec in enumerate(self.modalities)
        ]
        return torch.cat([t for t, _ in columns], dim=1), torch.cat([p for _, p in columns], dim=1)

    def _encode_modality(self, modality: int, obs: torch.Tensor, present: torch.Tensor, steps):
        """One modality's tokens ``[B, L_m, d]`` (zeros where absent) and their presence ``[B, L_m]``,
        from its window, presence ``[B]`` and, if given, step presence ``[B, H]``."""
        encoder = self.encoders[self.modalities[modality].name]
        if steps is not None:
            present = present & steps.any(1)
            obs = keys.zero_absent_steps(obs, steps)
        (tokens,) = compute_on_rows(
            present,
            lambda rows: (self.as_tokens(encoder(obs if rows is None else obs[rows])),),
            (self.absent_tokens(modality, present.shape[0], present.device),),
        )
        token_present = self._token_presence(modality, present, steps)
        if steps is not None:  # absent rows are zeros already; the tokens of absent steps are not
            tokens = tokens * token_present.unsqueeze(-1)
        return tokens, token_present

    def _token_presence(self, modality: int, present: torch.Tensor, steps: torch.Tensor | None):
        """Presence ``[B, L_m]`` of one modality's tokens: per step for a step-token encoder given
        ``present_steps``, else the modality's presence for every token."""
        encoder = self.encoders[self.modalities[modality].name]
        if steps is not None and getattr(encoder, "tokens_are_steps", False):
            return steps & present.unsqueeze(1)
        return present.unsqueeze(1).expand(-1, self.token_counts[modality])

    def modality_presence(self, token_present: torch.Tensor) -> torch.Tensor:
        """Token presence ``[N, num_tokens]`` -> modality presence ``[N, M]`` (any token present)."""
        return (token_present.unsqueeze(-1) & self.token_modality_one_hot).any(1)

    @staticmethod
    def as_tokens(encoded: torch.Tensor) -> torch.Tensor:
        """An encoder's output as tokens ``[N, L, d]`` (a one-token encoder returns ``[N, d]``)."""
        return encoded.unsqueeze(1) if encoded.dim() == 2 else encoded

    def absent_tokens(self, modality: int, rows: int, device: torch.device) -> torch.Tensor:
        """The zero tokens ``[rows, L_m, d]`` of an absent modality."""
        return torch.zeros(rows, self.token_counts[modality], self.config.d_model, device=device)

    @staticmethod
    def token_absent(present: torch.Tensor) -> torch.Tensor:
        """Token presence ``[N, num_tokens]`` -> the key-padding mask (True: absent token)."""
        return ~present

    def fuse(self, tokens: torch.Tensor, present: torch.Tensor, decoder_tokens: torch.Tensor | None = None):
        """The multimodal encoder: the flattened fused representation ``[N, out_rows × d]`` of ``N``
        rows of tokens ``[N, num_tokens, d]`` and presence ``[N, M]``. ``decoder_tokens``
        (:meth:`decoder_tokens` of the same rows), when given, spares mixing the tokens again."""
        absent = self.token_absent(present)
        if decoder_tokens is not None and self.decoder_reads_mixed:
            return self.fusion(tokens, absent, self.token_modality, mixed=decoder_tokens).flatten(1)
        return self.fusion(tokens, absent, self.token_modality).flatten(1)

    @property
    def decoder_reads_mixed(self) -> bool:
        """Whether the decoder reads the fusion's mixed tokens (``decoder_input="mixed"`` and a fusion
        with self-attention layers)."""
        return self.config.decoder_input == "mixed" and hasattr(self.fusion, "mix")

    @property
    def pair_streams_read_mixed(self) -> bool:
        """Whether the pair streams read the fusion's mixed tokens (``"mixed_pair_streams"`` and a fusion
        with self-attention layers)."""
        return self.config.decoder_input == "mixed_pair_streams" and hasattr(self.fusion, "mix")

    def decoder_tokens(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        """What the decoder reads of ``N`` rows of tokens and presence: the tokens after the multimodal
        encoder's self-attention layers when :attr:`decoder_reads_mixed` (so the fusion shapes every
        forecast), the ``M × M`` pair readouts with ``decoder_input="pair_streams"``, else the tokens
        themselves. Computed once a row, before rows are repeated for several latents or action
        sequences."""
        if self.pair_streams_read_mixed:
            tokens = self.fusion.mix(tokens, self.token_absent(present), self.token_modality)
        if self.pair_streams is not None:
            return self.pair_streams(tokens, present)
        if self.decoder_reads_mixed:
            return self.fusion.mix(tokens, self.token_absent(present), self.token_modality)
        return tokens

    def posterior(self, tokens: torch.Tensor, present: torch.Tensor, future: torch.Tensor | None):
        """``q(z | X[, y])``: ``loc``, ``scale`` ``[B, d_z]``. ``future`` is the target as the posterior
        reads it, :meth:`posterior_future` of the batch (``None`` for a posterior of ``X`` alone)."""
        return self._posterior_from(self.fuse(tokens, present), future)

    def prior(
        self, tokens: torch.Tensor, present: torch.Tensor, decoder_tokens: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``p(z | X)``: ``loc``, ``scale`` ``[N, d_z]`` (``0``, ``1`` under the standard prior, where
        the multimodal encoder does not run)."""
        if self.prior_head is None:
            return self._prior_from(None, tokens.shape[0], tokens.device)
        return self._prior_from(self.fuse(tokens, present, decoder_tokens), tokens.shape[0], tokens.device)

    def posterior_future(self, td: TensorDictBase, origin: torch.Tensor | None = None) -> torch.Tensor | None:
        """What the posterior ``q(z | X, y)`` reads of ``td``'s future ``[B, T, D]``: its ``"target"``, or
        with ``posterior_reads="residual"`` the target minus ``origin`` (:meth:`decode_origin`, computed
        when not given), the offset the decoder must produce; ``None`` when ``td`` has no target."""
        target = td.get(keys.TARGET, None)
        if target is None or self.config.posterior_reads == "target" or self.config.decode_from == "zero":
            return target
        return target - (self.decode_origin(td) if origin is None else origin)

    def _posterior_from(self, features: torch.Tensor, future: torch.Tensor | None):
        if self.target_encoder is not None:
            if future is None:
                raise KeyError(
                    f"the posterior q(z|X, y) needs {keys.TARGET!r} in the batch (in eval mode the "
                    "forecast needs no target; in training it does)"
                )
            features = torch.cat([features, self.target_encoder(future.flatten(1))], dim=-1)
        return latent_gaussian(self.posterior_head(features))

    def _prior_from(self, features: torch.Tensor | None, rows: int, device: torch.device):
        if self.prior_head is None:
            loc = torch.zeros(rows, self.config.d_latent, device=device)
            return loc, torch.ones_like(loc)
        return latent_gaussian(self.prior_head(features))

    def decode(
        self, tokens: torch.Tensor, present: torch.Tensor, z: torch.Tensor, action: torch.Tensor | None = None
    ):
        """``p(y | X, z[, a])``: ``loc``, ``scale`` ``[N, T, D]`` for ``N`` rows of tokens (as
        :meth:`encode` gives them), presence, ``z`` and, for a world model, the embedded action
        sequence (:meth:`embed_actions`)."""
        return self._decode_prepared(self.decoder_tokens(tokens, present), present, z, action)

    def _decode_prepared(self, decoder_tokens, present, z, action=None):
        """:meth:`decode` of rows whose :meth:`decoder_tokens` are already computed."""
        return self.decoder(decoder_tokens, *self.decoder_layout(present), z, action)

    def decoder_layout(self, present: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The key-padding mask ``[N, K]`` of the decoder's ``K`` tokens for token presence ``present``
        and the modality of each (``p^D`` it gets): the tokens', or the pairs' (absent unless both
        modalities are present; the query modality's ``p^D``)."""
        if self.pair_streams is None:
            return self.token_absent(present), self.token_modality
        pair_present = self.pair_streams.presence(self.modality_presence(present))
        return ~pair_present, self.pair_streams.pair_modality

    def forecast_from_tokens(
        self, tokens: torch.Tensor, present: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The eval forecast of encoded windows: what :meth:`forward` writes under ``("forecast",
        "loc"/"scale")`` in eval mode, ``[N, T, D]``, for tokens ``[N, M, d]`` and presence ``[N, M]``
        (:meth:`encode`; every row with a present modality).

        ``z`` from the prior by ``eval_latent``, then the decoder; nothing the forecast does not
        read runs (the posterior, and under the standard prior the multimodal encoder, which
        feeds only the posterior). No Python branch depends on the values of ``present``: one
        `torch.jit.trace` of it serves every presence pattern (`mmf_rl.rl.ForecastTransform`).
        """
        if self.action_encoder is not None:
            raise ValueError(
                "forecast_from_tokens: a world model forecasts under given actions; use decode_under_actions"
            )
        if self.config.decode_from != "zero":
            raise ValueError(
                f"forecast_from_tokens: decode_from={self.config.decode_from!r} offsets the forecast by the "
                "target's past, which encoded tokens do not carry; call the model on a batch with "
                f"{keys.TARGET_PAST!r} instead"
            )
        prepared = self.decoder_tokens(tokens, present)
        z = self._eval_latent(*self.eval_distribution(tokens, present, prepared))
        draws = z.shape[0] // tokens.shape[0]  # K with eval_latent="predictive", else 1
        loc, scale = moment_match(
            *self._decode_prepared(prepared.repeat(draws, 1, 1), present.repeat(draws, 1), z),
            draws,
            self.output_variance,
        )
        return loc, self.scale_calibration(scale, self.modality_presence(present))

    def embed_actions(self, td: TensorDictBase) -> torch.Tensor | None:
        """The action-sequence embedding ``[B, d]`` of a world model, ``None`` for a plain forecaster."""
        if self.action_encoder is None:
            return None
        return self.action_encoder(td.get(keys.FUTURE_ACTION).flatten(1))

    def _drop_mask(self, td: TensorDictBase) -> torch.Tensor | None:
        return keys.drop_masks(td, self.modalities)

    def _step_cuts(self, td: TensorDictBase) -> dict[int, torch.Tensor]:
        """The batch's ``("drop_steps", m)`` masks ``[B, H]`` (a modality without one has no cut), by
        modality index, checked."""
        cuts = {}
        for i, spec in enumerate(self.modalities):
            cut = td.get(keys.drop_steps_key(spec.name), None)
            if cut is None:
                continue
            expected = (td.batch_size[0], self.config.history)
            if spec.kind == "vector" or cut.dtype != torch.bool or tuple(cut.shape) != expected:
                raise ValueError(
                    f"td[{keys.drop_steps_key(spec.name)}]: expected bool {list(expected)} for a windowed "
                    f"modality, found {str(cut.dtype).removeprefix('torch.')} {list(cut.shape)} for "
                    f"{spec.name!r} ({spec.kind}); a single-vector modality has no steps to cut"
                )
            cuts[i] = cut
        return cuts

    def _cut_steps(self, td: TensorDictBase, tokens, kept, cuts: dict[int, torch.Tensor]):
        """The student's tokens and token presence with the ``("drop_steps", m)`` steps absent: each
        cut modality is encoded again, on its cut rows only, as :meth:`encode` would encode it with
        those steps absent in ``("present_steps", m)`` (zeroed for a whole-window encoder, masked
        tokens for a step-token encoder)."""
        token_columns, presence_columns = (
            list(tokens.split(self.token_counts, 1)),
            list(kept.split(self.token_counts, 1)),
        )
        for i, cut in cuts.items():
            spec = self.modalities[i]
            obs, present = td.get(spec.obs_key), td.get(spec.present_key)
            steps = td.get(keys.present_steps_key(spec.name), None)
            student_steps = ~cut if steps is None else steps & ~cut

            def encode_cut(rows, i=i, obs=obs, present=present, student_steps=student_steps):
                if rows is None:
                    return self._encode_modality(i, obs, present, student_steps)
                return self._encode_modality(i, obs[rows], present[rows], student_steps[rows])

            cut_tokens, cut_presence = compute_on_rows(
                cut.any(1), encode_cut, (token_columns[i], presence_columns[i])
            )
            token_columns[i] = cut_tokens
            presence_columns[i] = cut_presence & presence_columns[i]
        return torch.cat(token_columns, dim=1), torch.cat(presence_columns, dim=1)

    # -- TensorDict API --------------------------------------------------------------------------

    def forward(self, td: TensorDictBase) -> TensorDictBase:
        """Forecast ``td``'s windows (see the class docstring for what is read and written).

        Args:
            td (TensorDictBase): a batch ``[B]`` following `mmf_rl.keys`; written in place.

        Returns:
            ``td``, with the forecast, the latent and the distributions.
        """
        self.validate(td, require_target=self.training and self.target_encoder is not None)
        tokens, present = self.encode(td)
        tokens_kept, kept = self._student_input(td, tokens, present)
        origin = self.decode_origin(td)
        future = self.posterior_future(td, origin)
        wants_posterior = future is not None or self.target_encoder is None
        prepared = self.decoder_tokens(tokens, present)
        prepared_kept = None
        if kept is not None:
            prepared_kept = self._kept_decoder_tokens(tokens, tokens_kept, kept, prepared)
        features, prior_loc, prior_scale = self._fuse_with_prior(
            td, (tokens, present, prepared), (tokens_kept, kept, prepared_kept), wants_posterior
        )
        z = self._forward_latent(td, features, future, wants_posterior, (prior_loc, prior_scale))
        self._decode_into(td, (present, prepared), (kept, prepared_kept), z, (prior_loc, prior_scale), origin)
        return td

    def _decode_into(self, td: TensorDictBase, full, student, z: torch.Tensor, prior, origin) -> None:
        """Every decode of this pass, in one decoder call, written to ``td``: the full input at ``z``;
        the L_mis student at the same ``z``; the requested prior draws; each an offset from ``origin``
        (:meth:`decode_origin`). ``full`` and ``student`` are (token presence, decoder tokens), the
        student's ``(None, None)`` without ``("drop", m)``."""
        (present, prepared), (kept, prepared_kept), (prior_loc, prior_scale) = full, student, prior
        batch = present.shape[0]
        # A decode is a presence [B, M], its decoder tokens and its latents, B rows or K blocks of B.
        decodes = [(present, prepared, z)]
        if kept is not None:  # teacher and student share z (and the tokens of what was not cut)
            decodes.append((kept, prepared_kept, z))
        from_prior = keys.DECODE_FROM_PRIOR in td.keys()
        if from_prior:  # the GSNN term: a reparameterised prior draw, so the prior head learns from it
            decodes.append((present, prepared, prior_loc + prior_scale * torch.randn_like(prior_scale)))
        draws = self._requested_prior_draws(td)
        if draws:  # the best-of-K term: K reparameterised prior draws, rows k * B + b
            noise = torch.randn(draws * batch, prior_loc.shape[1], device=prior_loc.device)
            decodes.append(
                (present, prepared, prior_loc.repeat(draws, 1) + prior_scale.repeat(draws, 1) * noise)
            )
        decoded = self._decode_all(decodes, self.embed_actions(td), batch)
        if origin is not None:  # every decode of row b (rows k * B + b) is an offset from row b's origin
            decoded = [(loc + origin.repeat(loc.shape[0] // batch, 1, 1), scale) for loc, scale in decoded]
        if draws:  # kept apart, not mixed: the loss scores each draw's forecast
            samples = decoded.pop()[0]
            td.set(keys.FORECAST_FROM_PRIOR_SAMPLES, samples.unflatten(0, (draws, batch)).transpose(0, 1))
        forecasts = [
            moment_match(loc, scale, loc.shape[0] // batch, self.output_variance) for loc, scale in decoded
        ]
        td.set(keys.FORECAST_LOC, forecasts[0][0])
        td.set(keys.FORECAST_SCALE, self.scale_calibration(forecasts[0][1], self.modality_presence(present)))
        if kept is not None:
            td.set(keys.FORECAST_DROPPED_LOC, forecasts[1][0])
            td.set(keys.FORECAST_DROPPED_SCALE, forecasts[1][1])
        if from_prior:
            td.set(keys.FORECAST_FROM_PRIOR_LOC, forecasts[-1][0])
            td.set(keys.FORECAST_FROM_PRIOR_SCALE, forecasts[-1][1])

    def _kept_decoder_tokens(self, tokens, tokens_kept, kept: torch.Tensor, prepared: torch.Tensor):
        """The decoder tokens of the L_mis student (``tokens_kept``, ``kept``: its tokens and token
        presence). Without tail cuts the pair readouts are the full input's: a pair of two kept
        modalities reads the same tokens, the other pairs are masked out (:meth:`decoder_layout`)."""
        # Over mixed tokens a dropped modality changes what the kept ones mixed in: no reuse there.
        if self.pair_streams is not None and tokens_kept is tokens and not self.pair_streams_read_mixed:
            return prepared
        return self.decoder_tokens(tokens_kept, kept)

    def _student_input(self, td: TensorDictBase, tokens: torch.Tensor, present: torch.Tensor):
        """The L_mis student's tokens and token presence: the ``("drop", m)`` modalities removed and
        the ``("drop_steps", m)`` steps cut; ``(None, None)`` without masks."""
        drop, cuts = self._drop_mask(td), self._step_cuts(td)
        if drop is None:
            if cuts:
                raise KeyError(
                    "batch has ('drop_steps', m) masks without the ('drop', m) masks; give a ('drop', m) "
                    "for every modality (all False where only steps are cut)"
                )
            return None, None
        kept = present & ~drop[:, self.token_modality]
        if cuts:
            tokens, kept = self._cut_steps(td, tokens, kept, cuts)
        if not bool(kept.any(1).all()):
            raise ValueError(
                "('drop', m) with ('drop_steps', m) removes every present modality of some sample; keep "
                "at least one modality with one present step"
            )
        return tokens, kept

    def _fuse_with_prior(self, td: TensorDictBase, full, degraded, wants_posterior: bool):
        """The fused features (``None`` when neither a learned prior nor the posterior reads them)
        and the prior ``(loc, scale)``, written to ``td``; with a learned prior and ``("drop", m)``
        masks, the degraded input's prior too. ``full`` and ``degraded`` are (tokens, presence,
        decoder tokens) of the input and of the student's (``(None, None, None)`` without masks)."""
        (tokens, present, prepared), (tokens_kept, kept, prepared_kept) = full, degraded
        batch, device = present.shape[0], present.device
        learned = self.prior_head is not None
        features = None
        if learned and kept is not None:
            # The learned prior of the degraded input: the fusion of the kept modalities, in the
            # same pass (2B rows) as the full input's.
            both = torch.cat([present, kept])
            features, features_kept = self.fuse(
                torch.cat([tokens, tokens_kept]), both, torch.cat([prepared, prepared_kept])
            ).split(batch)
            prior_kept = self._prior_from(features_kept, batch, device)
            td.set(keys.PRIOR_DROPPED_LOC, prior_kept[0])
            td.set(keys.PRIOR_DROPPED_SCALE, prior_kept[1])
        elif learned or wants_posterior:
            features = self.fuse(tokens, present, prepared)
        prior_loc, prior_scale = self._prior_from(features, batch, device)
        td.set(keys.PRIOR_LOC, prior_loc)
        td.set(keys.PRIOR_SCALE, prior_scale)
        return features, prior_loc, prior_scale

    def _forward_latent(
        self, td: TensorDictBase, features, future, wants_posterior: bool, prior
    ) -> torch.Tensor:
        """The latent the forward decodes (a posterior draw in training, else ``eval_latent``'s),
        with the posterior (of ``future``, :meth:`posterior_future`) written to ``td`` when it is computed."""
        prior_loc, prior_scale = prior
        if wants_posterior:
            post_loc, post_scale = self._posterior_from(features, future)
            td.set(keys.POSTERIOR_LOC, post_loc)
            td.set(keys.POSTERIOR_SCALE, post_scale)
        if self.training:
            z = post_loc + post_scale * torch.randn_like(post_scale)
        elif self.config.eval_latent == "posterior":
            z = post_loc
        else:
            z = self._eval_latent(prior_loc, prior_scale)
        # K latents per sample (rows k * B + b) with eval_latent="predictive", else one.
        td.set(keys.LATENT, z if z.shape[0] == prior_loc.shape[0] else prior_loc)
        return z

    def _requested_prior_draws(self, td: TensorDictBase) -> int:
        """``K`` of the batch's ``"decode_prior_draws"`` request ``[B, K]`` (0 without one)."""
        request = td.get(keys.DECODE_PRIOR_DRAWS, None)
        if request is None:
            return 0
        if request.dim() != 2 or request.shape[1] < 1:
            raise ValueError(
                f"td[{keys.DECODE_PRIOR_DRAWS!r}]: expected [B, K] with K >= 1 prior draws per row, found "
                f"{list(request.shape)}"
            )
        return request.shape[1]

    def _decode_all(self, decodes: list, action: torch.Tensor | None, batch: int) -> list:
        """``(loc, scale)`` of each decode ``(presence, decoder tokens, latents)``, in one decoder call:
        as many rows as the decode's latents."""
        present, prepared, z = decodes[0]
        rows = [latent.shape[0] for *_, latent in decodes]
        copies = sum(rows) // batch
        if copies == 1:
            loc, scale = self._decode_prepared(prepared, present, z, action)
        else:
            loc, scale = self._decode_prepared(
                torch.cat([t.repeat(latent.shape[0] // batch, 1, 1) for _, t, latent in decodes]),
                torch.cat([p.repeat(latent.shape[0] // batch, 1) for p, _, latent in decodes]),
                torch.cat([latent for *_, latent in decodes]),
                None if action is None else action.repeat(copies, 1),
            )
        return list(zip(loc.split(rows), scale.split(rows), strict=True))

    def sample(self, td: TensorDictBase, num_samples: int = 20) -> TensorDictBase:
        """Decode ``num_samples`` latents drawn from :meth:`eval_distribution` (the prior ``p(z | X)``,
        or ``q(z | X)`` with ``eval_latent="posterior"``) in one batched pass; with a learned sampler of
        ``K = num_samples`` codes, decode its codes instead (:meth:`learned_samples`).

        Writes ``("forecast", "samples")`` ``[B, K, T, D]``: the mean of ``p(y | X, z_k)`` for each
        ``z_k``. Other outputs are left untouched. Use under ``torch.no_grad()`` for evaluation.

        Args:
            td (TensorDictBase): a batch following `mmf_rl.keys`; written in place.
            num_samples (int, optional): ``K``. Defaults to ``20``.

        Returns:
            ``td``.
        """
        if num_samples < 1:
            raise ValueError(f"num_samples must be >= 1, found {num_samples}")
        if self.latent_sampler is not None and num_samples == self.latent_sampler.num_samples:
            td.set(keys.FORECAST_SAMPLES, self.learned_samples(td)[0])
            return td
        self.validate(td)
        tokens, present = self.encode(td)
        batch = present.shape[0]
        prepared = self.decoder_tokens(tokens, present)
        prior_loc, prior_scale = self.eval_distribution(tokens, present, prepared)
        # Row k * B + b is sample k of batch element b.
        noise = torch.randn(num_samples * batch, self.config.d_latent, device=present.device)
        z = prior_loc.repeat(num_samples, 1) + prior_scale.repeat(num_samples, 1) * noise
        td.set(keys.FORECAST_SAMPLES, self._decode_draws(td, prepared, present, z))
        return td

    def _decode_draws(self, td: TensorDictBase, prepared, present, z: torch.Tensor) -> torch.Tensor:
        """The decoder's means ``[B, K, T, D]`` of ``B`` prepared histories under ``K × B`` latents ``z``
        (row ``k * B + b``: latent ``k`` of history ``b``), with ``td``'s actions for a world model."""
        batch = present.shape[0]
        draws = z.shape[0] // batch
        action = self.embed_actions(td)
        loc, _ = self._decode_prepared(
            prepared.repeat(draws, 1, 1),
            present.repeat(draws, 1),
            z,
            None if action is None else action.repeat(draws, 1),
        )
        means = loc.view(draws, batch, *loc.shape[1:]).transpose(0, 1)
        origin = self.decode_origin(td)
        return means if origin is None else means + origin.unsqueeze(1)

    def learned_samples(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The learned sampler's ``K`` forecasts of ``td``'s histories: their means ``[B, K, T, D]``, and
        its codes and spreads ``[B, K, d_z]`` in the prior's standard coordinates (the KL term's).

        The history's encoding runs without gradient (the sampler trains on a frozen forecaster); the
        decoder runs with it, so that the forecasts' loss reaches the codes."""
        if self.latent_sampler is None:
            raise ValueError(
                "learned_samples: this forecaster has no learned sampler; build it with "
                "model.learned_samples=K and train it with sampler.steps > 0"
            )
        self.validate(td)
        with torch.no_grad():
            tokens, present = self.encode(td)
            prepared = self.decoder_tokens(tokens, present)
            features = self.fuse(tokens, present, prepared)
            prior_loc, prior_scale = self._prior_from(features, features.shape[0], features.device)
        codes, spreads = self.latent_sampler(features)
        # Row k * B + b is code k of history b, as in sample.
        z = (prior_loc.unsqueeze(1) + prior_scale.unsqueeze(1) * codes).transpose(0, 1).flatten(0, 1)
        return self._decode_draws(td, prepared, present, z), codes, spreads

    @contextlib.contextmanager
    def drawing_from_the_prior(self):
        """Within it, :meth:`sample` draws from the prior even with a learned sampler: to compare the two."""
        sampler, self.latent_sampler = self.latent_sampler, None
        try:
            yield self
        finally:
            self.latent_sampler = sampler

    def forecast_under_actions(
        self, td: TensorDictBase, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """A world model's forecasts for ``N`` candidate action sequences per history.

        ``td`` holds ``B`` history windows (its ``"future_action"``, if any, is ignored);
        ``actions`` is ``[B, N, S, A]`` in the normalised frame of ``"future_action"``. Each
        history is encoded once and decoded for its ``N`` sequences in one batched pass (a
        planner that scores several batches of candidates for one history calls :meth:`encode`
        once and :meth:`decode_under_actions` per batch).

        Args:
            td (TensorDictBase): ``B`` history windows following `mmf_rl.keys`.
            actions (torch.Tensor): ``[B, N, S, A]`` candidate action sequences, normalised.

        Returns:
            ``loc``, ``scale`` ``[B, N, T, D]``.
        """
        self._require_actions("forecast_under_actions")
        keys.validate_batch(td, self.modalities, self.config.history, nonfinite=self.config.nonfinite)
        if self.config.nonfinite == "absent":
            keys.mark_nonfinite_absent(td, self.modalities)
        return self.decode_under_actions(*self.encode(td), actions)

    def decode_under_actions(
        self, tokens: torch.Tensor, present: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Decode encoded histories under action sequences, ``z`` from the prior by ``eval_latent`` (its
        mean by default; ``"predictive"`` decodes ``B × N × K`` rows in one pass and moment-matches
        them).

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens ``[B, N, d]``.
            present (torch.Tensor): its token presence ``[B, N]``.
            actions (torch.Tensor): ``[B, N', S, A]`` normalised action sequences, ``N'`` per history.

        Returns:
            ``loc``, ``scale`` ``[B, N', T, D]``.

        Raises:
            ValueError: a model without action input, or ``actions`` of another shape.
        """
        self._require_actions("decode_under_actions")
        expected = (tokens.shape[0], *self.config.action_shape)
        if actions.dim() != 4 or (actions.shape[0], *actions.shape[2:]) != expected:
            raise ValueError(
                f"actions: expected [B, N, S, A] = [{expected[0]}, N, {expected[1]}, {expected[2]}], "
                f"found {list(actions.shape)}"
            )
        batch, candidates = actions.shape[:2]
        prepared = self.decoder_tokens(tokens, present)  # once per history, not per candidate
        loc, scale = self.eval_distribution(tokens, present, prepared)
        z = self._eval_latent(loc.repeat_interleave(candidates, 0), scale.repeat_interleave(candidates, 0))
        draws = z.shape[0] // (batch * candidates)  # K with eval_latent="predictive", else 1
        embedded = self.action_encoder(actions.reshape(batch * candidates, -1))
        present = present.repeat_interleave(candidates, 0)
        loc, scale = moment_match(
            *self._decode_prepared(
                prepared.repeat_interleave(candidates, 0).repeat(draws, 1, 1),
                present.repeat(draws, 1),
                z,
                embedded.repeat(draws, 1),
            ),
            draws,
            self.output_variance,
        )
        scale = self.scale_calibration(scale, self.modality_presence(present))
        return loc.view(batch, candidates, *loc.shape[1:]), scale.view(batch, candidates, *scale.shape[1:])

    def eval_distribution(
        self, tokens: torch.Tensor, present: torch.Tensor, decoder_tokens: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The latent distribution eval decodes from: ``q(z | X)`` with ``eval_latent="posterior"``
        (eqs. 10 and 15 read literally), else the prior ``p(z | X)``.

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens.
            present (torch.Tensor): its token presence.
            decoder_tokens (torch.Tensor, optional): :meth:`decoder_tokens` of them, when already
                computed.

        Returns:
            ``loc``, ``scale`` ``[B, d_z]``.
        """
        if self.config.eval_latent == "posterior":
            return self._posterior_from(self.fuse(tokens, present, decoder_tokens), None)
        return self.prior(tokens, present, decoder_tokens)

    def _eval_latent(self, prior_loc: torch.Tensor, prior_scale: torch.Tensor) -> torch.Tensor:
        """The eval-mode latents of ``N`` prior rows by ``eval_latent``: ``[N, d_z]``, the prior's mean
        (``"mean"``) or a draw (``"sample"``); ``[K × N, d_z]`` for ``"predictive"``, row ``k * N + n``
        ``= μ_n + σ_n ε_k`` with the fixed ``ε_k`` of ``predictive_noise``."""
        if self.config.eval_latent in ("mean", "posterior"):
            return prior_loc
        if self.config.eval_latent == "sample":
            return prior_loc + prior_scale * torch.randn_like(prior_scale)
        noise = self.predictive_noise
        if noise.shape[0] != self.config.predictive_samples:
            raise ValueError(
                f"model.config.predictive_samples={self.config.predictive_samples} was set after the model "
                f"was built with {noise.shape[0]}; set it in the ForecasterConfig the model is built from"
            )
        return (prior_loc + prior_scale * noise.unsqueeze(1)).flatten(0, 1)

    def _require_actions(self, method: str) -> None:
        if self.action_encoder is None:
            raise ValueError(
                f"{method} needs an action-conditioned model: this forecaster was built without "
                "action_dim (train it with `action` set in the data config)"
            )
