"""Simulated multimodal push: the MuJoCo env, its scripted pusher, its TorchRL env and sensor outages.

Importing this package selects the offscreen OpenGL backend (`MUJOCO_GL`, EGL else OSMesa)
unless the caller already set it.
"""

import gymnasium

from mmf_rl.envs.push import MultimodalPushEnv
from mmf_rl.envs.scripted import MarkovPusher, PusherStyle, ScriptedPusher, rollout

ENV_ID = "mmf_rl/MultimodalPush-v0"

if ENV_ID not in gymnasium.registry:
    # FetchPush's own time limit: 50 steps, 2 s at 25 Hz.
    gymnasium.register(ENV_ID, entry_point=MultimodalPushEnv, max_episode_steps=50)

# Lazy for start-up time only: the TorchRL side imports torchrl (seconds), which the recorder's
# worker processes, importing the MuJoCo env alone, never need.
_TORCHRL_EXPORTS = {
    "MultimodalPushTorchEnv": "mmf_rl.envs.torchrl_env",
    "ModalityDropout": "mmf_rl.envs.modality_dropout",
    "UniformBursts": "mmf_rl.envs.modality_dropout",
    "GeometricBursts": "mmf_rl.envs.modality_dropout",
    "outage_start_prob": "mmf_rl.envs.modality_dropout",
    "replay_outages": "mmf_rl.envs.modality_dropout",
}

__all__ = [
    "ENV_ID",
    "MarkovPusher",
    "MultimodalPushEnv",
    "PusherStyle",
    "ScriptedPusher",
    "rollout",
    *_TORCHRL_EXPORTS,
]


def __getattr__(name):
    if name not in _TORCHRL_EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(_TORCHRL_EXPORTS[name]), name)
