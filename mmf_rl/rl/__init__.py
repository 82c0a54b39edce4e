"""The forecaster in reinforcement learning: live-forecast (and latched-forecast) and history
transforms, the world model (and an ensemble of them), a model-based env for torchrl's planners,
a vectorised CEM planner for model-predictive control with the push task's objective, the MPC agent the
recorder records with (`PushMPCAgent`), and behaviour cloning from recorded demonstrations with the
forecast as a policy input (action chunks with temporal ensembling: `action_chunks`), trained on
outages drawn per sample (or by an `OutageSampler`). The push experiments built on them
(``benchmarks/mpc_push.py``, ``benchmarks/bc_push.py``) live beside the package, in
``benchmarks/push/``."""

from mmf_rl.rl.agent import MPCActor, PushMPCAgent
from mmf_rl.rl.bc import DEFAULT_DROPOUT, BCConfig, BCPolicy, EncoderChoice, train_bc, validation_errors
from mmf_rl.rl.cem import SequenceCEMPlanner
from mmf_rl.rl.demonstrations import (
    DemonstrationLoader,
    Demonstrations,
    ForecastTable,
    OutageSampler,
    drop_sets,
)
from mmf_rl.rl.ensemble_world_model import EnsembleWorldModel
from mmf_rl.rl.latched_forecast import LatchedForecastTable, LatchedForecastTransform
from mmf_rl.rl.push_objective import PushObjective
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow
from mmf_rl.rl.world_model import WorldModel
from mmf_rl.rl.world_model_env import ForecasterWorldModelEnv, ImaginedPlanningPolicy

__all__ = [
    "DEFAULT_DROPOUT",
    "BCConfig",
    "BCPolicy",
    "DemonstrationLoader",
    "Demonstrations",
    "EncoderChoice",
    "EnsembleWorldModel",
    "ForecastTable",
    "ForecastTransform",
    "ForecasterWorldModelEnv",
    "HistoryWindow",
    "ImaginedPlanningPolicy",
    "LatchedForecastTable",
    "LatchedForecastTransform",
    "MPCActor",
    "OutageSampler",
    "PushMPCAgent",
    "PushObjective",
    "SequenceCEMPlanner",
    "WorldModel",
    "drop_sets",
    "train_bc",
    "validation_errors",
]
