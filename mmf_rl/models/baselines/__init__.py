"""Baselines of the paper's robot table, with the forecaster's batch contract: LF-LSTM, MVAE, MulT;
and constant velocity, the parameter-free reference of trajectory forecasting."""

from mmf_rl.models.baselines.common import BaselineConfig
from mmf_rl.models.baselines.constant_velocity import ConstantVelocity, ConstantVelocityConfig
from mmf_rl.models.baselines.lf_lstm import LateFusionLSTM, LFLSTMConfig
from mmf_rl.models.baselines.mult import MulT, MulTConfig
from mmf_rl.models.baselines.mvae import MVAE, MVAEConfig

__all__ = [
    "BaselineConfig",
    "ConstantVelocity",
    "ConstantVelocityConfig",
    "LFLSTMConfig",
    "LateFusionLSTM",
    "MVAE",
    "MVAEConfig",
    "MulT",
    "MulTConfig",
]
