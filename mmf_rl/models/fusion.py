"""Ablations of the forecaster's multimodal encoder (paper Table 4, "Fusion").

Each replaces :class:`~mmf_rl.models.forecaster.modeling_forecaster.ModalityAgnosticEncoder`
(``fusion="agnostic"``) and nothing else: the same call ``fusion(tokens [B, M, d], absent [B, M])``
and an output ``[B, out_rows, d]`` that the posterior head flattens. Tokens of absent modalities
are zeros (the forecaster's encode step) and every fusion also masks them itself, so no
value under an absent modality reaches the output.

* ``linear``: the ``M`` tokens concatenated (absent ones zero) through one linear layer.
* ``average``: the mean of the present tokens.
* ``sum``: the sum of the present tokens.
* ``cross_attention`` (CXA, Qiu et al. 2022): each present modality's token attends to the
  other present modalities' tokens (pre-LN, residual, MLP); absent rows are zero.
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

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        return self.linear(_present_tokens(tokens, absent).flatten(1)).view_as(tokens)


class AverageFusion(nn.Module):
    out_rows = 1

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        count = (~absent).sum(1, keepdim=True).clamp_min(1).unsqueeze(-1)
        return _present_tokens(tokens, absent).sum(1, keepdim=True) / count


class SumFusion(nn.Module):
    out_rows = 1

    def forward(self, tokens: torch.Tensor, absent: torch.Tensor) -> torch.Tensor:
        return _present_tokens(tokens, absent).sum(1, keepdim=True)


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
        return _present_tokens(x, absent)


def build_fusion(kind: str, num_modalities: int, d_model: int, num_heads: int, mlp_hidden: int) -> nn.Module:
    """An ablation fusion by name (``"agnostic"`` is built by the forecaster itself)."""
    if kind == "linear":
        return LinearFusion(num_modalities, d_model)
    if kind == "average":
        return AverageFusion()
    if kind == "sum":
        return SumFusion()
    if kind == "cross_attention":
        return CrossAttentionFusion(num_modalities, d_model, num_heads, mlp_hidden)
    raise ValueError(f"unknown fusion {kind!r}; expected one of {FUSIONS}")
