"""Attention blocks of the forecaster and the baselines (pre-LN, key-padding masks).

Absent modalities are padded token slots: ``key_padding_mask`` is ``True`` where a token is
absent, so one batch can mix presence patterns in a single pass.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from mmf_rl.models.encoders import mlp


def batch_first_attention(
    attn: nn.MultiheadAttention,
    query: torch.Tensor,
    source: torch.Tensor,
    key_padding_mask: torch.Tensor | None,
) -> torch.Tensor:
    """``attn(query, source, source, key_padding_mask=..., need_weights=False)[0]`` for a module built
    batch-first with the defaults (packed in-projection with biases, no dropout), computed in the
    batch-first layout: ``query`` ``[B, L, d]`` attends to ``source`` ``[B, S, d]`` (``query`` itself
    for self-attention); ``key_padding_mask`` ``[B, S]`` is True where a key is hidden.

    The module's own path turns batch-first inputs sequence-first and back, so every projection
    reads a transposed copy and every output is copied back, in the forward and again in the
    backward: at small batches a large share of a training step's ops. Here the same weights, the
    same projections and ``scaled_dot_product_attention`` run on the batch-first tensors: the same
    forward values, and gradients equal up to float rounding (their sums run over the rows in
    another order)."""
    batch, length, width = query.shape
    heads = attn.num_heads
    split = (heads, width // heads)
    if query is source:  # one packed projection, as the module does for self-attention
        projected = F.linear(query, attn.in_proj_weight, attn.in_proj_bias)
        q, k, v = projected.view(batch, length, 3, *split).permute(2, 0, 3, 1, 4)
    else:
        w_q, w_kv = attn.in_proj_weight.split([width, 2 * width])
        b_q, b_kv = attn.in_proj_bias.split([width, 2 * width])
        q = F.linear(query, w_q, b_q).view(batch, length, *split).transpose(1, 2)
        projected = F.linear(source, w_kv, b_kv)
        k, v = projected.view(batch, source.shape[1], 2, *split).permute(2, 0, 3, 1, 4)
    mask = None
    if key_padding_mask is not None:  # the additive mask the module makes of a boolean one
        mask = torch.zeros(key_padding_mask.shape, dtype=query.dtype, device=query.device)
        mask = mask.masked_fill_(key_padding_mask, float("-inf")).view(batch, 1, 1, -1)
    out = F.scaled_dot_product_attention(q, k, v, mask)
    return attn.out_proj(out.transpose(1, 2).reshape(batch, length, width))


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
        x = x + batch_first_attention(self.attn, h, h, key_padding_mask)
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
        out = batch_first_attention(self.attn, self.norm_query(query), self.norm_kv(tokens), key_padding_mask)
        return out + residual


class CrossModalLayer(nn.Module):
    """Pre-LN cross-modal block (MulT): ``Q = Q + MHA(LN(Q), LN(S), LN(S))``; ``Q = Q + MLP(LN(Q))``.

    ``key_padding_mask`` ``[B, L_S]`` (True: an absent source token) hides source tokens; a row must
    keep at least one (attention over no key is undefined)."""

    def __init__(self, d_model: int, num_heads: int, mlp_hidden: int):
        super().__init__()
        self.norm_query = nn.LayerNorm(d_model)
        self.norm_source = nn.LayerNorm(d_model)
        self.attn = nn.MultiheadAttention(d_model, num_heads, batch_first=True)
        self.norm_mlp = nn.LayerNorm(d_model)
        self.mlp = mlp(d_model, mlp_hidden, d_model)

    def forward(
        self, query: torch.Tensor, source: torch.Tensor, key_padding_mask: torch.Tensor | None = None
    ) -> torch.Tensor:
        attended = batch_first_attention(
            self.attn, self.norm_query(query), self.norm_source(source), key_padding_mask
        )
        query = query + attended
        return query + self.mlp(self.norm_mlp(query))


class PairStreams(nn.Module):
    """MulT's pair streams as tokens: one readout ``[B, d]`` per ordered modality pair ``(i, j)``.

    For each of the ``M × M`` pairs (``i == j`` included, so a lone modality keeps a readout), a
    cross-modal layer of its own lets modality ``i``'s **last present** token attend to ``j``'s present
    tokens; its output is the pair's readout. One layer, so a query's output depends on its own token
    and the keys only: computing the readout's query alone gives what the full stream gives there.
    Absent tokens (an absent modality, or an absent step of a step-token encoder) are hidden from the
    keys and never read as the query, so what is stored under them changes nothing. A pair is absent
    (:meth:`presence`) when ``i`` or ``j`` has no present token; its readout is then a placeholder
    the caller masks out. ``self_pairs="alone"``: a self pair ``i <- i`` is present only when ``i`` is
    the only present modality (MulT's pair set whenever two or more are present).
    """

    def __init__(
        self,
        token_counts: list[int],
        d_model: int,
        num_heads: int,
        mlp_hidden: int,
        self_pairs: str = "always",
    ):
        super().__init__()
        m = len(token_counts)
        self.token_counts = list(token_counts)
        self.self_pairs = self_pairs
        self.pairs = [(i, j) for i in range(m) for j in range(m)]
        self.layers = nn.ModuleList(CrossModalLayer(d_model, num_heads, mlp_hidden) for _ in self.pairs)
        pair_index = torch.tensor(self.pairs)
        # The query modality i of each pair: the modality embedding its readout gets in the decoder.
        self.register_buffer("pair_modality", pair_index[:, 0].clone(), persistent=False)
        self.register_buffer("pair_source", pair_index[:, 1].clone(), persistent=False)

    def forward(self, tokens: torch.Tensor, token_present: torch.Tensor) -> torch.Tensor:
        """Tokens ``[B, N, d]`` (in modality order, ``token_counts`` each) and their presence ``[B, N]``
        -> readouts ``[B, M × M, d]``, pair ``(i, j)`` at row ``i × M + j``."""
        # Zeros under absent tokens: an absent pair's placeholder depends on nothing stored there either.
        tokens = tokens.masked_fill(~token_present.unsqueeze(-1), 0.0)
        columns = tokens.split(self.token_counts, dim=1)
        presence = token_present.split(self.token_counts, dim=1)
        queries = [last_present_token(c, p) for c, p in zip(columns, presence, strict=True)]
        # A row whose j is absent attends to j's zero tokens instead of to no key (a NaN): its pair is
        # absent, so the readout is masked out downstream.
        hidden = [~p & p.any(1, keepdim=True) for p in presence]
        readouts = [
            layer(queries[i], columns[j], hidden[j])[:, 0]
            for layer, (i, j) in zip(self.layers, self.pairs, strict=True)
        ]
        return torch.stack(readouts, dim=1)

    def presence(self, modality_present: torch.Tensor) -> torch.Tensor:
        """Modality presence ``[B, M]`` -> pair presence ``[B, M × M]`` (both ``i`` and ``j`` present;
        with ``self_pairs="alone"``, a self pair only when its modality is the only one present)."""
        present = modality_present[:, self.pair_modality] & modality_present[:, self.pair_source]
        if self.self_pairs == "alone":
            alone = modality_present.sum(1, keepdim=True) == 1
            present = present & ((self.pair_modality != self.pair_source) | alone)
        return present


def last_present_token(tokens: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """``[B, 1, d]``: each row's last present token of ``tokens`` ``[B, L, d]`` (presence ``[B, L]``);
    the first token where none is present."""
    position = torch.arange(1, present.shape[1] + 1, device=present.device)
    last = (present.long() * position).argmax(1)
    return tokens.gather(1, last.view(-1, 1, 1).expand(-1, 1, tokens.shape[-1]))
