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
    """:class:`BaselineConfig` of :class:`LateFusionLSTM`; the LSTMs' hidden size is ``d_model``.

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

    Raises:
        ValueError: no modality, duplicate names, an unknown encoder, a size below 1, ``min_scale <= 0``,
            an unknown ``nonfinite`` or ``output_distribution``, or ``output_df <= 2`` with ``"student_t"``.
    """


@register_model("lf_lstm", LFLSTMConfig, loss=("nll",))
class LateFusionLSTM(DeterministicForecaster):
    """Per-modality encoders and LSTMs, late concatenation, MLP head (see module docstring).

    Reads ``("obs", m)`` and ``("present", m)``, absent modalities zero-filled; writes
    ``("forecast", "loc"/"scale")`` and, given ``("drop", m)`` masks, ``("forecast_dropped", ...)``.
    Trained with :class:`~mmf_rl.objectives.GaussianNLLLoss` (its registry entry's loss).

    Args:
        config (LFLSTMConfig): the sizes.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models.baselines import LateFusionLSTM, LFLSTMConfig
        >>> force, pose = ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))
        >>> model = LateFusionLSTM(LFLSTMConfig([force, pose], history=4, horizon=5, d_model=16)).eval()
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(3, 4, 6),
        ...     ("present", "force"): torch.tensor([True, True, False]),  # the third sample lost it
        ...     ("obs", "pose"): torch.randn(3, 3),
        ...     ("present", "pose"): torch.ones(3, dtype=torch.bool),
        ... }, batch_size=[3])
        >>> out = model(batch)
        >>> out["forecast", "loc"].shape, out["forecast", "scale"].shape
        (torch.Size([3, 5, 2]), torch.Size([3, 5, 2]))
    """

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
