"""Attention blocks of the paper's multimodal encoder and decoder (pre-LN, key-padding masks).

Absent modalities are padded token slots: ``key_padding_mask`` is ``True`` where a token is
absent, so one batch can mix presence patterns in a single pass.
"""

from __future__ import annotations

import torch
from torch import nn

from mmf_rl.models.encoders import mlp


class PreLNTransformerLayer(nn.Module):
    """``X' = MSA(LN(X)) + X``; ``X = MLP(LN(X')) + X'`` (paper eqs. for layers ``1..L-1``)."""

    def __init__(self, d_model: int, num_heads: int, mlp_hidden: int):
        super().__init__()
        self.norm_attn = nn.LayerNorm(d_model)
        self.attn = nn.MultiheadAttention(d_model, num_heads, batch_first=True)
        self.norm_mlp = nn.LayerNorm(d_model)
        self.mlp = mlp(d_model, mlp_hidden, d_model)

    def forward(self, x: torch.Tensor, key_padding_mask: torch.Tensor) -> torch.Tensor:
        h = self.norm_attn(x)
        x = x + self.attn(h, h, h, key_padding_mask=key_padding_mask, need_weights=False)[0]
        return x + self.mlp(self.norm_mlp(x))


class FixedQueryAttention(nn.Module):
    """``MHA(LN(Q), LN(X), LN(X)) + R``: attention from a fixed set of ``M`` queries.

    The output always has ``M`` rows whatever the number of present tokens, which is what makes
    the aggregation modality-agnostic. ``R`` is the residual: the paper adds the block's input
    ``X``, whose row count (present modalities) differs from the output's (``M``); we add the
    queries instead, as the Set Transformer's pooling block (Lee et al. 2019, which the paper
    cites for this scheme) does. The caller passes the residual explicitly.
    """

    def __init__(self, d_model: int, num_heads: int):
        super().__init__()
        self.norm_query = nn.LayerNorm(d_model)
        self.norm_kv = nn.LayerNorm(d_model)
        self.attn = nn.MultiheadAttention(d_model, num_heads, batch_first=True)

    def forward(
        self,
        query: torch.Tensor,
        tokens: torch.Tensor,
        key_padding_mask: torch.Tensor,
        residual: torch.Tensor,
    ) -> torch.Tensor:
        kv = self.norm_kv(tokens)
        out = self.attn(
            self.norm_query(query), kv, kv, key_padding_mask=key_padding_mask, need_weights=False
        )[0]
        return out + residual
