"""LF-LSTM: MultiBench's late-fusion baseline for ``gentle_push`` (Liang et al. 2021).

Each modality: per-step encoder -> its own LSTM over the ``H`` steps -> last hidden state. The
``M`` states are concatenated (late fusion) and an MLP head outputs the Gaussian over ``T × D``.
Absent modalities follow the zero-fill protocol (:func:`~mmf_rl.models.baselines.common.zero_filled`):
the model has no notion of presence, as in MultiBench.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

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
class LFLSTMConfig(BaselineConfig):
    """:class:`BaselineConfig`; the LSTMs' hidden size is ``d_model``."""


@register_model("lf_lstm", LFLSTMConfig, loss=("nll",))
class LateFusionLSTM(DeterministicForecaster):
    """Per-modality encoders and LSTMs, late concatenation, MLP head (see module docstring)."""

    def __init__(self, config: LFLSTMConfig):
        super().__init__(config)
        d = config.d_model
        self.tokenizers = nn.ModuleDict({s.name: StepTokenizer(s, d) for s in self.modalities})
        self.lstms = nn.ModuleDict({s.name: nn.LSTM(d, d, batch_first=True) for s in self.modalities})
        self.head = mlp(len(self.modalities) * d, config.head_hidden, 2 * config.horizon * config.target_dim)

    def forecast(self, td):
        states = []
        for spec in self.modalities:
            tokens = self.tokenizers[spec.name](zero_filled(td, spec))
            states.append(self.lstms[spec.name](tokens)[1][0][-1])
        cfg = self.config
        return gaussian_head_output(
            self.head(torch.cat(states, dim=-1)), cfg.horizon, cfg.target_dim, cfg.min_scale
        )
