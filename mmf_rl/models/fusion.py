"""Fusions: how the forecaster aggregates a variable set of modality tokens into ``M`` rows.

A fusion maps tokens ``[B, N, d]`` (``N >= M``: an encoder may emit one token per step), their
absence ``[B, N]`` (True: absent, a key-padding mask) and the modality of each token ``[N]`` to
``[B, M, d]``, whatever the presence pattern. The forecaster builds one per place it aggregates:
the multimodal encoder (``role="encoder"``, feeding the posterior and a learned prior) and the
decoder (``role="decoder"``, feeding the output head), so ``model.fusion`` swaps the aggregation
in both places (paper Table 4). Every fusion hands the heads the same ``M × d`` features.

A new fusion is one module plus one ``@register_fusion(name)`` on its builder
``build(shape: FusionShape) -> nn.Module``. Built in:

* ``agnostic`` (the paper): fixed queries over the present tokens (modality-agnostic attention).
  Its encoder side is :class:`ModalityAgnosticEncoder`; its decoder side is the decoder's own two
  attentions from the queries ``P^D`` (eqs. 12-14), which live in the decoder because ``P^D`` is
  also the embedding the decoder adds to its tokens.
* ``linear``: the ``N`` tokens concatenated (absent ones zero) through one linear layer to ``M`` rows.
* ``average``: the mean of the present tokens, repeated on the ``M`` rows.
* ``sum``: the sum of the present tokens, normalised, repeated on the ``M`` rows.
* ``cross_attention`` (CXA, Qiu et al. 2022): each present token attends to the tokens of the
  *other* present modalities (pre-LN, residual, MLP); a modality's row is the mean of its tokens,
  zero when it is absent.

Output scale: ``linear``, ``sum`` and ``cross_attention`` end in a LayerNorm over each row. Without
it their output's scale followed the number of present modalities, and the learned prior's
degraded-input term (which compares the fusion of all modalities with the fusion of fewer)
dominated training. ``average`` and ``agnostic`` are convex combinations of normalised or bounded
tokens and need none (normalised, ``average`` would be ``sum``: a LayerNorm is scale-invariant).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from mmf_rl.models.attention import FixedQueryAttention, PreLNTransformerLayer
from mmf_rl.models.encoders import mlp


@dataclass(frozen=True)
class FusionShape:
    """What a fusion is built for: ``M`` modalities, ``N`` tokens, widths, and its place."""

    num_modalities: int
    num_tokens: int
    d_model: int
    num_heads: int
    mlp_hidden: int
    num_layers: int  # the forecaster's L (num_encoder_layers)
    role: Literal["encoder", "decoder"]


FusionBuilder = Callable[[FusionShape], nn.Module]
FUSIONS: dict[str, FusionBuilder] = {}


def register_fusion(name: str) -> Callable[[FusionBuilder], FusionBuilder]:
    """Register ``build(shape: FusionShape) -> nn.Module`` as fusion ``name``."""

    def register(build: FusionBuilder) -> FusionBuilder:
        if name in FUSIONS:
            raise ValueError(f"fusion {name!r} is already registered")
        FUSIONS[name] = build
        return build

    return register


def check_fusion(name: str) -> None:
    """A clear error unless ``name`` is a registered fusion."""
    if name not in FUSIONS:
        raise ValueError(
            f"unknown fusion {name!r}; expected one of {sorted(FUSIONS)} (a new one is registered with "
            "@mmf_rl.models.fusion.register_fusion(name))"
        )


def build_fusion(name: str, shape: FusionShape) -> nn.Module:
    """The registered fusion ``name`` for ``shape``."""
    check_fusion(name)
    return FUSIONS[name](shape)


class ModalityAgnosticEncoder(nn.Module):
    """The paper's multimodal encoder: ``+ P^E``, ``L - 1`` self-attention layers over the present
    tokens (:meth:`mix`), then the fixed queries ``P^E`` over them and an MLP (:meth:`pool`)."""

    def __init__(self, shape: FusionShape):
        super().__init__()
        d, m = shape.d_model, shape.num_modalities
        self.out_rows = m
        self.modality_embedding = nn.Parameter(torch.randn(m, d) * 0.02)  # P^E
        self.layers = nn.ModuleList(
            PreLNTransformerLayer(d, shape.num_heads, shape.mlp_hidden) for _ in range(shape.num_layers - 1)
        )
        self.aggregate = FixedQueryAttention(d, shape.num_heads)
        self.norm_mlp = nn.LayerNorm(d)
        self.mlp = mlp(d, shape.mlp_hidden, d)

    def mix(self, tokens: torch.Tensor, absent: torch.Tensor, token_modality: torch.Tensor) -> torch.Tensor:
        """The tokens with ``P^E`` after the self-attention layers: ``[B, N, d]``, cross-modally mixed."""
        x = tokens + self.modality_embedding[token_modality]
        for layer in self.layers:
            x = layer(x, absent)
        return x

    def pool(self, mixed: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        queries = self.modality_embedding.expand(mixed.shape[0], -1, -1)
        x = self.aggregate(queries, mixed, absent, residual=queries)
        return x + self.mlp(self.norm_mlp(x))

    def forward(
        self,
        tokens: torch.Tensor,
        absent: torch.Tensor,
        token_modality: torch.Tensor,
        mixed: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """``mixed``: :meth:`mix` of these tokens when the caller has it already (the decoder reads it)."""
        return self.pool(self.mix(tokens, absent, token_modality) if mixed is None else mixed, absent)


@register_fusion("agnostic")
def agnostic_fusion(shape: FusionShape) -> nn.Module | None:
    # None on the decoder side: the decoder's own attention from P^D (module docstring).
    return ModalityAgnosticEncoder(shape) if shape.role == "encoder" else None


def _present_tokens(tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
    return tokens.masked_fill(absent.unsqueeze(-1), 0.0)


class LinearFusion(nn.Module):
    def __init__(self, shape: FusionShape):
        super().__init__()
        self.out_rows, d = shape.num_modalities, shape.d_model
        self.linear = nn.Linear(shape.num_tokens * d, self.out_rows * d)
        self.output_norm = nn.LayerNorm(d)

    def forward(
        self, tokens: torch.Tensor, absent: torch.Tensor, token_modality: torch.Tensor
    ) -> torch.Tensor:
        fused = self.linear(_present_tokens(tokens, absent).flatten(1))
        return self.output_norm(fused.view(tokens.shape[0], self.out_rows, -1))


class AverageFusion(nn.Module):
    def __init__(self, shape: FusionShape):
        super().__init__()
        self.out_rows = shape.num_modalities

    def forward(
        self, tokens: torch.Tensor, absent: torch.Tensor, token_modality: torch.Tensor
    ) -> torch.Tensor:
        count = (~absent).sum(1, keepdim=True).clamp_min(1).unsqueeze(-1)
        mean = _present_tokens(tokens, absent).sum(1, keepdim=True) / count
        return mean.expand(-1, self.out_rows, -1)


class SumFusion(nn.Module):
    def __init__(self, shape: FusionShape):
        super().__init__()
        self.out_rows = shape.num_modalities
        self.output_norm = nn.LayerNorm(shape.d_model)

    def forward(
        self, tokens: torch.Tensor, absent: torch.Tensor, token_modality: torch.Tensor
    ) -> torch.Tensor:
        total = self.output_norm(_present_tokens(tokens, absent).sum(1, keepdim=True))
        return total.expand(-1, self.out_rows, -1)


class CrossAttentionFusion(nn.Module):
    """Each token attends to the tokens of the *other* present modalities (a sample with a single
    present modality attends to its own: attention over an empty set is undefined)."""

    def __init__(self, shape: FusionShape):
        super().__init__()
        d, m = shape.d_model, shape.num_modalities
        self.out_rows = m
        self.modality_embedding = nn.Parameter(torch.randn(m, d) * 0.02)
        self.norm_query = nn.LayerNorm(d)
        self.norm_kv = nn.LayerNorm(d)
        self.attn = nn.MultiheadAttention(d, shape.num_heads, batch_first=True)
        self.norm_mlp = nn.LayerNorm(d)
        self.mlp = mlp(d, shape.mlp_hidden, d)
        self.output_norm = nn.LayerNorm(d)

    def forward(
        self, tokens: torch.Tensor, absent: torch.Tensor, token_modality: torch.Tensor
    ) -> torch.Tensor:
        x = _present_tokens(tokens, absent) + self.modality_embedding[token_modality]
        kv = self.norm_kv(x)
        mask = self._mask(absent, token_modality)
        x = x + self.attn(self.norm_query(x), kv, kv, attn_mask=mask, need_weights=False)[0]
        x = _present_tokens(self.output_norm(x + self.mlp(self.norm_mlp(x))), absent)
        # A modality's row: the mean of its present tokens (zero when absent).
        member = nn.functional.one_hot(token_modality, self.out_rows).to(x.dtype)  # [N, M]
        counts = (member.unsqueeze(0) * (~absent).unsqueeze(-1).to(x.dtype)).sum(1).clamp_min(1)
        return torch.einsum("bnd,nm->bmd", x, member) / counts.unsqueeze(-1)

    def _mask(self, absent: torch.Tensor, token_modality: torch.Tensor) -> torch.Tensor:
        # [B * heads, N(query), N(key)]: True where the key is hidden from the query.
        same = token_modality.unsqueeze(0) == token_modality.unsqueeze(1)
        present_modalities = (~absent).unsqueeze(-1) & nn.functional.one_hot(token_modality).bool()
        has_other = (present_modalities.any(1).sum(1) >= 2).view(-1, 1, 1)
        hidden = absent.unsqueeze(1) | (same & has_other)
        return hidden.repeat_interleave(self.attn.num_heads, dim=0)


register_fusion("linear")(LinearFusion)
register_fusion("average")(AverageFusion)
register_fusion("sum")(SumFusion)
register_fusion("cross_attention")(CrossAttentionFusion)
