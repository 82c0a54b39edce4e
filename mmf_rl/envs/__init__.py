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

__all__ = ["ENV_ID", "MultimodalPushEnv", "PusherStyle", "ScriptedPusher", "rollout"]
