"""Planning with an action-conditioned forecaster (world model): model-predictive control."""

from mmf_rl.planning.cem import SequenceCEMPlanner
from mmf_rl.planning.push_objective import PushObjective
from mmf_rl.planning.world_model import WorldModel

__all__ = ["PushObjective", "SequenceCEMPlanner", "WorldModel"]
