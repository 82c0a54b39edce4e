"""The hybrids of MulT and the paper model that ``benchmarks/mult_gap.py`` trains, each registered as a
model under a ``gap_*`` name when this module runs.

Each swaps one part of MulT for the paper model's, or one part of the paper model for MulT's, so the
benchmark's table attributes MulT's all-sensor lead on push. They exist for that experiment only, so
they live beside its script, not among the package's models: the script runs this module each time it
runs (its ``--jobs`` workers, which run the script again, too), and a checkpoint of a hybrid loads only
where this module has run (in ``mmf-rl eval`` or ``load_trained_model`` it is an unknown model).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from mmf_rl.models.attention import FixedQueryAttention
from mmf_rl.models.baselines.common import gaussian_head_output, zero_filled
from mmf_rl.models.baselines.mult import CrossModalLayer, CrossModalTransformer, MulT, MulTConfig
from mmf_rl.models.encoders import StepTokens, build_encoder, mlp
from mmf_rl.models.forecaster.configuration_forecaster import ForecasterConfig
from mmf_rl.models.forecaster.modeling_forecaster import ModalitySpecificDecoder, MultimodalForecaster
from mmf_rl.models.fusion import FusionShape
from mmf_rl.models.registry import register_model

# --- hybrids of MulT ---------------------------------------------------------------------------------


class StagedMulT(MulT):
    """MulT with its forecast in three stages a hybrid can replace one at a time: the modalities'
    token sequences, the pairs' last-step readouts, and the head's input made of them."""

    def modality_tokens(self, td) -> dict[str, torch.Tensor]:
        """``{m: [N, L_m, d]}``: each tokenizer's tokens (a window encoder's one token is the last step)
        plus MulT's step embedding, unless the tokenizer adds its own (the paper's ``StepTokens``)."""
        tokens = {}
        for spec in self.modalities:
            tokenizer = self.tokenizers[spec.name]
            seq = tokenizer(zero_filled(td, spec))
            seq = seq.unsqueeze(1) if seq.dim() == 2 else seq
            own_embedding = isinstance(tokenizer, StepTokens)
            tokens[spec.name] = seq if own_embedding else seq + self.step_embedding[-seq.shape[1] :]
        return tokens

    def pair_readouts(self, tokens: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        """The last token ``[N, d]`` of each ordered pair's cross-modal stream ``i <- j``."""
        return [self.streams[f"{i}<-{j}"](tokens[i], tokens[j])[:, -1] for i, j in self.pairs]

    def head_input(self, readouts: list[torch.Tensor]) -> torch.Tensor:
        return torch.cat(readouts, dim=-1)

    def forecast(self, td):
        cfg = self.config
        raw = self.head(self.head_input(self.pair_readouts(self.modality_tokens(td))))
        return gaussian_head_output(raw, cfg.horizon, cfg.target_dim, cfg.min_scale)


@register_model("gap_mult_fq", MulTConfig, loss=("nll",))
class MulTFixedQueryReadout(StagedMulT):
    """Swaps MulT's readout: the pairs' last-step readouts are aggregated by the paper decoder's two
    fixed-query attentions (``M`` learned queries; the second refines the first) and the ``M`` rows
    flattened into the head, instead of concatenated. Tokens and pair streams stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d, m = config.d_model, len(self.modalities)
        self.queries = nn.Parameter(torch.randn(m, d) * 0.02)
        self.aggregate = FixedQueryAttention(d, config.num_heads)
        self.refine = FixedQueryAttention(d, config.num_heads)
        self.head = mlp(m * d, config.head_hidden, 2 * config.horizon * config.target_dim)

    def head_input(self, readouts: list[torch.Tensor]) -> torch.Tensor:
        h0 = torch.stack(readouts, dim=1)
        # Zero-fill: an absent modality is a zero signal, so no readout is masked out.
        none_absent = torch.zeros(h0.shape[:2], dtype=torch.bool, device=h0.device)
        queries = self.queries.expand(h0.shape[0], -1, -1)
        h1 = self.aggregate(queries, h0, none_absent, residual=queries)
        return self.refine(h1, h0, none_absent, residual=h1).flatten(1)


@register_model("gap_mult_tok1", MulTConfig, loss=("nll",))
class MulTOnPaperTokens(StagedMulT):
    """Swaps MulT's tokens: the paper's unimodal encoders (``build_encoder``, one token per modality's
    window) feed MulT's pair streams, whose readouts are concatenated into MulT's head."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d = config.d_model
        self.tokenizers = nn.ModuleDict(
            {s.name: build_encoder(s, config.history, d) for s in self.modalities}
        )
        del self.step_embedding  # one token per modality: no steps to tell apart

    def modality_tokens(self, td) -> dict[str, torch.Tensor]:
        return {s.name: self.tokenizers[s.name](zero_filled(td, s)).unsqueeze(1) for s in self.modalities}


@register_model("gap_mult_tok1_fq", MulTConfig, loss=("nll",))
class MulTOnPaperTokensFixedQueryReadout(MulTOnPaperTokens, MulTFixedQueryReadout):
    """Both swaps: the paper's one-token encoders feed MulT's pair streams, whose readouts the
    paper decoder's two fixed-query attentions aggregate."""


@register_model("gap_mult_shared", MulTConfig, loss=("nll",))
class MulTSharedPairLayer(MulTOnPaperTokens):
    """:class:`MulTOnPaperTokens` with one cross-modal layer shared by every pair (a learned pair
    embedding added to its query says which pair it serves) instead of one Transformer per pair."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d = config.d_model
        self.shared = CrossModalLayer(d, config.num_heads, config.mlp_hidden)
        self.pair_embedding = nn.Parameter(torch.randn(len(self.pairs), d) * 0.02)
        del self.streams

    def pair_readouts(self, tokens: dict[str, torch.Tensor]) -> list[torch.Tensor]:
        return [
            self.shared(tokens[i] + self.pair_embedding[k], tokens[j])[:, -1]
            for k, (i, j) in enumerate(self.pairs)
        ]


@register_model("gap_mult_stackimg", MulTConfig, loss=("nll",))
class MulTStackedImageToken(StagedMulT):
    """Swaps MulT's image tokens only: the camera window becomes one token of the paper's
    frame-stacked ConvNet (with the last step's embedding); the vectors keep MulT's per-step tokens,
    pair streams and concatenated head."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        for spec in self.modalities:
            if spec.kind == "image":
                self.tokenizers[spec.name] = build_encoder(spec, config.history, config.d_model)


@register_model("gap_mult_self", MulTConfig, loss=("nll",))
class MulTWithSelfPairs(StagedMulT):
    """Swaps MulT's pair set for the paper pair-stream decoder's: all ``M × M`` ordered pairs, the
    self pairs ``i <- i`` included, each with its own cross-modal Transformer; the ``M²`` readouts
    are concatenated into a head as much wider. Tokens and readout stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        names = [s.name for s in self.modalities]
        d = config.d_model
        self.pairs = [(i, j) for i in names for j in names]
        self.streams = nn.ModuleDict(
            {
                f"{i}<-{j}": CrossModalTransformer(d, config.num_heads, config.mlp_hidden, config.num_layers)
                for i, j in self.pairs
            }
        )
        self.head = mlp(len(self.pairs) * d, config.head_hidden, 2 * config.horizon * config.target_dim)


@register_model("gap_mult_steptok", MulTConfig, loss=("nll",))
class MulTOnPaperStepTokens(StagedMulT):
    """Swaps MulT's vector tokenizer (a linear layer + ReLU per step, one step embedding shared by the
    modalities) for the paper's ``steps`` encoder (a two-layer MLP per step, a step embedding per
    modality). The image keeps MulT's per-frame tokens; pair streams and head stay MulT's."""

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        for spec in self.modalities:
            if spec.kind == "sequence":
                self.tokenizers[spec.name] = StepTokens(spec, config.history, config.d_model)


# --- hybrids of the paper model ----------------------------------------------------------------------


class TokenFeatures(nn.Module):
    """In place of the decoder's joint MLP: a token's own ``d`` features (with ``P^D``), ``z`` dropped."""

    def __init__(self, d_model: int):
        super().__init__()
        self.d_model = d_model

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        return joint[..., : self.d_model]


class PerModalityJoint(nn.Module):
    """The decoder's joint MLP with one set of weights per modality, applied to its tokens."""

    def __init__(self, token_counts: list[int], in_dim: int, hidden: int, out_dim: int):
        super().__init__()
        self.token_counts = token_counts
        self.mlps = nn.ModuleList(mlp(in_dim, hidden, out_dim) for _ in token_counts)

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        # Tokens come in modality order (MultimodalForecaster.encode).
        columns = joint.split(self.token_counts, dim=1)
        return torch.cat([f(x) for f, x in zip(self.mlps, columns, strict=True)], dim=1)


class ResidualJoint(nn.Module):
    """The decoder's joint MLP as a residual branch: a token's ``d`` features plus the MLP's output."""

    def __init__(self, joint: nn.Module, d_model: int):
        super().__init__()
        self.joint, self.d_model = joint, d_model

    def forward(self, joint: torch.Tensor) -> torch.Tensor:
        return joint[..., : self.d_model] + self.joint(joint)


@register_model("gap_fc_nojoint", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterWithoutJoint(MultimodalForecaster):
    """The paper model whose decoder has no joint MLP: the tokens plus ``P^D`` go straight into its
    fixed-query attentions and ``z`` is unused. Everything else stays."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        self.decoder.joint = TokenFeatures(config.d_model)


@register_model("gap_fc_pm", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPerModalityJoint(MultimodalForecaster):
    """The paper model with one decoder joint MLP per modality instead of one shared by all; its
    tokens, attentions and head stay."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        d = config.d_model
        self.decoder.joint = PerModalityJoint(self.token_counts, d + config.d_latent, config.mlp_hidden, d)


@register_model("gap_fc_res", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterResidualJoint(MultimodalForecaster):
    """The paper model whose decoder joint MLP is a residual branch (a token keeps its own features);
    everything else stays."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        self.decoder.joint = ResidualJoint(self.decoder.joint, config.d_model)


@register_model("gap_fc_pair", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPairTokens(MultimodalForecaster):
    """The paper model whose decoder reads MulT's pair structure: ``M × M`` tokens, token ``i <- j`` a
    cross-modal layer of its own from modality ``i``'s token to ``j``'s (``i <- i``: itself), absent
    when ``i`` or ``j`` is; ``P^D`` of ``i`` is added to it. The decoder's joint MLP, fixed-query
    attentions and head stay. Needs one token per modality and ``decoder_input="tokens"``."""

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        if config.decoder_input != "tokens" or set(self.token_counts) != {1}:
            raise ValueError(
                "gap_fc_pair builds pair tokens from one raw token per modality: set "
                "model.decoder_input=tokens and one-token encoders (conv, mlp, gru)"
            )
        m, d = len(self.modalities), config.d_model
        self.pair_index = [(i, j) for i in range(m) for j in range(m)]
        self.pair_layers = nn.ModuleList(
            CrossModalLayer(d, config.num_heads, config.mlp_hidden) for _ in self.pair_index
        )
        self.register_buffer("pair_modality", torch.tensor([i for i, _ in self.pair_index]), persistent=False)

    def decoder_tokens(self, tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
        pairs = zip(self.pair_layers, self.pair_index, strict=True)
        return torch.stack(
            [layer(tokens[:, i : i + 1], tokens[:, j : j + 1])[:, 0] for layer, (i, j) in pairs], dim=1
        )

    def _decode_prepared(self, decoder_tokens, present, z, action=None):
        absent = torch.stack([~(present[:, i] & present[:, j]) for i, j in self.pair_index], dim=1)
        return self.decoder(decoder_tokens, absent, self.pair_modality, z, action)


class WideDecoder(ModalitySpecificDecoder):
    """The paper's decoder with ``queries_per_modality × M`` learned queries (the head reads all their
    rows) and, with ``post_mlp``, a residual pre-LN MLP after each of its two attentions."""

    def __init__(self, cfg: ForecasterConfig, shape: FusionShape, queries_per_modality: int, post_mlp: bool):
        super().__init__(cfg, shape)
        if self.fusion is not None:
            raise ValueError(f"a wide decoder widens the paper's attention; model.fusion={cfg.fusion!r}")
        m, d = len(cfg.modalities), cfg.d_model
        self.queries = nn.Parameter(torch.randn(queries_per_modality * m, d) * 0.02)
        self.head = mlp(queries_per_modality * m * d, cfg.head_hidden, 2 * cfg.horizon * cfg.target_dim)
        self.post = (
            nn.ModuleList(nn.Sequential(nn.LayerNorm(d), mlp(d, cfg.mlp_hidden, d)) for _ in range(2))
            if post_mlp
            else None
        )

    def forward(self, tokens, absent, token_modality, z, action=None):
        n = tokens.shape[0]
        h0 = self.joint_tokens(tokens, token_modality, z, action)
        queries = self.queries.expand(n, -1, -1)
        h1 = self.aggregate(queries, h0, absent, residual=queries)
        h1 = h1 if self.post is None else h1 + self.post[0](h1)
        h2 = self.refine(h1, h0, absent, residual=h1)
        h2 = h2 if self.post is None else h2 + self.post[1](h2)
        loc, raw_scale = self.head(h2.flatten(1)).view(n, 2, *self.out_shape).unbind(1)
        return loc, F.softplus(raw_scale) + self.min_scale


class ForecasterWideDecoder(MultimodalForecaster):
    """The paper model with a :class:`WideDecoder` of the class's ``queries_per_modality`` and
    ``post_mlp``; the encoders and the multimodal encoder stay."""

    queries_per_modality = 1
    post_mlp = False

    def __init__(self, config: ForecasterConfig):
        super().__init__(config)
        shape = FusionShape(
            num_modalities=len(self.modalities),
            num_tokens=sum(self.token_counts),
            d_model=config.d_model,
            num_heads=config.num_heads,
            mlp_hidden=config.mlp_hidden,
            num_layers=config.num_encoder_layers,
            role="decoder",
        )
        self.decoder = WideDecoder(config, shape, self.queries_per_modality, self.post_mlp)


@register_model("gap_fc_q4", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterFourQueries(ForecasterWideDecoder):
    """The paper model whose decoder aggregates with 4 learned queries per modality instead of ``P^D``'s
    one (the head reads ``4 M`` rows); everything before the decoder's attentions stays."""

    queries_per_modality = 4


@register_model("gap_fc_post", ForecasterConfig, loss=("elbo", "mis"))
class ForecasterPostAggregationMLP(ForecasterWideDecoder):
    """The paper model whose decoder has a residual MLP after each of its two attentions (its queries
    learned apart from ``P^D``); everything before the decoder's attentions stays."""

    post_mlp = True
