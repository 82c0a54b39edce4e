"""Ablations of the forecaster's multimodal encoder (paper Table 4, "Fusion").

Each replaces :class:`~mmf_rl.models.forecaster.modeling_forecaster.ModalityAgnosticEncoder`
(``fusion="agnostic"``) and nothing else: the same call ``fusion(tokens [B, M, d], absent [B, M])``
and an output ``[B, out_rows, d]`` that the posterior head (and the learned prior's head) flattens.
Tokens of absent modalities are zeros (the forecaster's encode step) and every fusion also masks
them itself, so no value under an absent modality reaches the output.

* ``linear``: the ``M`` tokens concatenated (absent ones zero) through one linear layer, read as
  ``M`` rows (each a mix of every present token).
* ``average``: the mean of the present tokens.
* ``sum``: the sum of the present tokens.
* ``cross_attention`` (CXA, Qiu et al. 2022): each present modality's token attends to the
  other present modalities' tokens (pre-LN, residual, MLP); absent rows are zero.

**Output scale.** The agnostic encoder ends without a LayerNorm, but its output's scale does not
depend on the tokens' scale nor on how many modalities are present: its last block attends from
fixed queries over LayerNormed tokens (a convex combination) with the queries as residual. Linear,
sum and cross-attention passed the unnormalised token scale through, sum and linear scaled by the
number of present modalities, cross-attention in its residual stream. With the learned prior that
broke training (issue #13): ``loss_mis_prior`` ties the prior of the full input to the prior of
the input minus dropped modalities, their fused features differed in scale, the term and its
gradient grew by orders of magnitude, took nearly all of each clipped step, and the forecasts
collapsed to the training mean. So these three end in a LayerNorm over each output row
(``output_norm``): every row reaches the heads on one scale whatever the tokens' scale and the
number of present modalities. A LayerNorm on the tokens before the fusion (the agnostic encoder's
pre-LN) is not enough: in a short gradient diagnostic on the push data sum stayed scaled by the
count and linear's weights grew the scale back. Cross-attention's absent rows stay zero (no value
under an absent modality reaches the output), so a dropped modality still removes a whole row of
its flattened features, and its degraded-input prior term trains down more slowly than the other
fusions'.

``average`` has no output norm: like the agnostic pooling it is a convex combination of the
tokens, and it trained without one. With one it would be the same function as ``sum``: a
LayerNorm is scale-invariant, so ``LN(Σ x) = LN(mean x)``; normalised, ``sum`` is the mean of the
present tokens on a fixed scale, which is all of a sum that the learned prior can train with.
"""

from __future__ import annotations

import torch
from torch import nn

from mmf_rl.models.encoders import mlp

FUSIONS = ("agnostic", "linear", "average", "sum", "cross_attention")


def _present_tokens(tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
    return tokens.masked_fill(absent.unsqueeze(-1), 0.0)


class LinearFusion(nn.Module):
    def __init__(self, num_modalities: int, d_model: int):
        super().__init__()
        self.out_rows = num_modalities
        self.linear = nn.Linear(num_modalities * d_model, num_modalities * d_model)
        self.output_norm = nn.LayerNorm(d_model)

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        return self.output_norm(self.linear(_present_tokens(tokens, absent).flatten(1)).view_as(tokens))


class AverageFusion(nn.Module):
    # No output_norm: bounded like the agnostic pooling; normalised it would equal sum (module docstring).
    out_rows = 1

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        count = (~absent).sum(1, keepdim=True).clamp_min(1).unsqueeze(-1)
        return _present_tokens(tokens, absent).sum(1, keepdim=True) / count


class SumFusion(nn.Module):
    out_rows = 1

    def __init__(self, d_model: int):
        super().__init__()
        self.output_norm = nn.LayerNorm(d_model)

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        return self.output_norm(_present_tokens(tokens, absent).sum(1, keepdim=True))


class CrossAttentionFusion(nn.Module):
    """Each modality attends to the *other* present modalities (a sample with a single present
    modality attends to itself: attention over an empty set is undefined)."""

    def __init__(self, num_modalities: int, d_model: int, num_heads: int, mlp_hidden: int):
        super().__init__()
        self.out_rows = num_modalities
        self.modality_embedding = nn.Parameter(torch.randn(num_modalities, d_model) * 0.02)
        self.norm_query = nn.LayerNorm(d_model)
        self.norm_kv = nn.LayerNorm(d_model)
        self.attn = nn.MultiheadAttention(d_model, num_heads, batch_first=True)
        self.norm_mlp = nn.LayerNorm(d_model)
        self.mlp = mlp(d_model, mlp_hidden, d_model)
        self.output_norm = nn.LayerNorm(d_model)

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        batch, m, _ = tokens.shape
        x = _present_tokens(tokens, absent) + self.modality_embedding
        eye = torch.eye(m, dtype=torch.bool, device=tokens.device)
        has_other = ((~absent).sum(1) >= 2).view(batch, 1, 1)
        # [B, M(query), M(key)]: True where the key is hidden from the query.
        hidden = absent.unsqueeze(1) | (eye & has_other)
        heads = self.attn.num_heads
        mask = hidden.repeat_interleave(heads, dim=0)
        q, kv = self.norm_query(x), self.norm_kv(x)
        x = x + self.attn(q, kv, kv, attn_mask=mask, need_weights=False)[0]
        x = x + self.mlp(self.norm_mlp(x))
        return _present_tokens(self.output_norm(x), absent)


def build_fusion(kind: str, num_modalities: int, d_model: int, num_heads: int, mlp_hidden: int) -> nn.Module:
    """An ablation fusion by name (``"agnostic"`` is built by the forecaster itself)."""
    if kind == "linear":
        return LinearFusion(num_modalities, d_model)
    if kind == "average":
        return AverageFusion()
    if kind == "sum":
        return SumFusion(d_model)
    if kind == "cross_attention":
        return CrossAttentionFusion(num_modalities, d_model, num_heads, mlp_hidden)
    raise ValueError(f"unknown fusion {kind!r}; expected one of {FUSIONS}")
