"""The forecaster in reinforcement learning: live-forecast and history transforms, the world model,
a model-based env for torchrl's planners, and a vectorised CEM planner for model-predictive control."""

from mmf_rl.rl.cem import SequenceCEMPlanner
from mmf_rl.rl.push_objective import PushObjective
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow
from mmf_rl.rl.world_model import WorldModel
from mmf_rl.rl.world_model_env import ForecasterWorldModelEnv, ImaginedPlanningPolicy

__all__ = [
    "ForecastTransform",
    "ForecasterWorldModelEnv",
    "HistoryWindow",
    "ImaginedPlanningPolicy",
    "PushObjective",
    "SequenceCEMPlanner",
    "WorldModel",
]
