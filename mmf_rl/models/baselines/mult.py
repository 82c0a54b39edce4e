"""MulT: pairwise cross-modal Transformers (Tsai et al. 2019), small.

Each modality's window becomes a token sequence (per-step encoder + learned step embedding).
For every ordered pair ``(target i, source j)``, ``i != j``, a cross-modal Transformer lets
``i``'s tokens attend to ``j``'s: ``M (M - 1)`` streams. Each stream's last token is kept
(MulT's "last element" readout), the ``M (M - 1)`` vectors are concatenated and an MLP head
outputs the Gaussian over ``T × D``. With a single modality the stream is its self-attention.
Absent modalities follow the zero-fill protocol, as in MulT's handling of unaligned/missing
inputs by padding.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from mmf_rl.models.attention import CrossModalLayer
from mmf_rl.models.baselines.common import (
    BaselineConfig,
    DeterministicForecaster,
    StepTokenizer,
    gaussian_head_output,
    zero_filled,
)
from mmf_rl.models.encoders import mlp
from mmf_rl.models.registry import register_model


@dataclass
class MulTConfig(BaselineConfig):
    """:class:`BaselineConfig` of :class:`MulT`, plus the cross-modal Transformers' sizes.

    Args:
        modalities (list[ModalitySpec]): one :class:`ModalitySpec` per input modality (at least one).
        history (int, optional): ``H``, past steps per window. Defaults to ``10``.
        horizon (int, optional): ``T``, future steps forecast. Defaults to ``10``.
        target_dim (int, optional): ``D``, dims of the forecast variable. Defaults to ``2``.
        d_model (int, optional): width of every per-modality representation. Defaults to ``64``.
        head_hidden (int, optional): hidden width of the output head. Defaults to ``256``.
        min_scale (float, optional): floor added to every predicted scale. Defaults to
            ``1e-3``.
        nonfinite (str, optional): NaN/Inf under a present modality: ``"raise"`` (default) or
            ``"absent"`` (read as absent), as :func:`mmf_rl.keys.mark_nonfinite_absent` applies it.
        output_distribution (str, optional): the family the forecast's ``(loc, scale)`` is read with:
            ``"normal"`` (default), ``"laplace"`` or ``"student_t"`` (:mod:`mmf_rl.objectives.distributions`).
        output_df (float, optional): the degrees of freedom of ``"student_t"`` (``> 2``). Defaults to ``4``.
        num_heads (int, optional): attention heads (``d_model`` must divide by it). Defaults to ``4``.
        num_layers (int, optional): layers per cross-modal Transformer. Defaults to ``1``.
        mlp_hidden (int, optional): their feed-forward width. Defaults to ``128``.

    Raises:
        ValueError: no modality, duplicate names, an unknown encoder, a size below 1, ``min_scale <= 0``,
            an unknown ``nonfinite`` or ``output_distribution``, ``output_df <= 2`` with ``"student_t"``, or
            ``d_model`` not divisible by ``num_heads``.
    """

    num_heads: int = 4
    num_layers: int = 1
    mlp_hidden: int = 128

    def __post_init__(self):
        super().__post_init__()
        if self.d_model % self.num_heads:
            raise ValueError(
                f"MulTConfig: d_model={self.d_model} must be divisible by num_heads={self.num_heads}"
            )


class CrossModalTransformer(nn.Module):
    def __init__(self, d_model: int, num_heads: int, mlp_hidden: int, num_layers: int):
        super().__init__()
        self.layers = nn.ModuleList(
            CrossModalLayer(d_model, num_heads, mlp_hidden) for _ in range(num_layers)
        )

    def forward(self, query: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            query = layer(query, source)
        return query


@register_model("mult", MulTConfig, loss=("nll",))
class MulT(DeterministicForecaster):
    """Pairwise cross-modal attention, concatenation, MLP head (see module docstring).

    Reads ``("obs", m)`` and ``("present", m)``, absent modalities zero-filled; writes
    ``("forecast", "loc"/"scale")`` and, given ``("drop", m)`` masks, ``("forecast_dropped", ...)``.
    Trained with :class:`~mmf_rl.objectives.GaussianNLLLoss` (its registry entry's loss).

    Args:
        config (MulTConfig): the sizes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models.baselines import MulT, MulTConfig
        >>> force, pose = ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))
        >>> model = MulT(MulTConfig([force, pose], history=4, horizon=5, d_model=16, num_heads=2)).eval()
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(3, 4, 6),
        ...     ("present", "force"): torch.tensor([True, True, False]),  # the third sample lost it
        ...     ("obs", "pose"): torch.randn(3, 3),
        ...     ("present", "pose"): torch.ones(3, dtype=torch.bool),
        ... }, batch_size=[3])
        >>> model(batch)["forecast", "loc"].shape
        torch.Size([3, 5, 2])
    """

    def __init__(self, config: MulTConfig):
        super().__init__(config)
        d = config.d_model
        names = [s.name for s in self.modalities]
        self.tokenizers = nn.ModuleDict({s.name: StepTokenizer(s, d) for s in self.modalities})
        self.step_embedding = nn.Parameter(torch.randn(config.history, d) * 0.02)
        self.pairs = [(i, j) for i in names for j in names if i != j] or [(names[0], names[0])]
        self.streams = nn.ModuleDict(
            {
                f"{i}<-{j}": CrossModalTransformer(d, config.num_heads, config.mlp_hidden, config.num_layers)
                for i, j in self.pairs
            }
        )
        self.head = mlp(len(self.pairs) * d, config.head_hidden, 2 * config.horizon * config.target_dim)

    def forecast(self, td):
        tokens = {}
        for spec in self.modalities:
            seq = self.tokenizers[spec.name](zero_filled(td, spec))
            tokens[spec.name] = seq + self.step_embedding[-seq.shape[1] :]  # a single vector is the last step
        readouts = [self.streams[f"{i}<-{j}"](tokens[i], tokens[j])[:, -1] for i, j in self.pairs]
        cfg = self.config
        return gaussian_head_output(
            self.head(torch.cat(readouts, dim=-1)), cfg.horizon, cfg.target_dim, cfg.min_scale
        )
