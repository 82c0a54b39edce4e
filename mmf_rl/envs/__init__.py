"""Simulated multimodal push: the MuJoCo env, its scripted pusher and a gymnasium id.

Importing this package selects the offscreen OpenGL backend (`MUJOCO_GL`, EGL else OSMesa)
unless the caller already set it.
"""

import gymnasium

from mmf_rl.envs.push import MultimodalPushEnv
from mmf_rl.envs.scripted import PusherStyle, ScriptedPusher, rollout

ENV_ID = "mmf_rl/MultimodalPush-v0"

if ENV_ID not in gymnasium.registry:
    # FetchPush's own time limit: 50 steps, 2 s at 25 Hz.
    gymnasium.register(ENV_ID, entry_point=MultimodalPushEnv, max_episode_steps=50)

# The TorchRL side imports torchrl and the models; it loads on first use so that importing the
# MuJoCo env alone (e.g. in the recorder's worker processes) stays cheap.
_TORCHRL_EXPORTS = {
    "MultimodalPushTorchEnv": "mmf_rl.envs.torchrl_env",
    "ModalityDropout": "mmf_rl.envs.transforms",
    "UniformBursts": "mmf_rl.envs.transforms",
    "GeometricBursts": "mmf_rl.envs.transforms",
    "outage_start_prob": "mmf_rl.envs.transforms",
    "replay_outages": "mmf_rl.envs.transforms",
    "ForecastTransform": "mmf_rl.envs.transforms",
    "HistoryWindow": "mmf_rl.envs.transforms",
    "ForecasterWorldModelEnv": "mmf_rl.envs.world_model",
    "ImaginedPlanningPolicy": "mmf_rl.envs.world_model",
}

__all__ = ["ENV_ID", "MultimodalPushEnv", "PusherStyle", "ScriptedPusher", "rollout", *_TORCHRL_EXPORTS]


def __getattr__(name):
    if name not in _TORCHRL_EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_TORCHRL_EXPORTS[name]), name)
