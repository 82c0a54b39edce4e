"""The multimodal push task as a TorchRL env that speaks the `mmf_rl.keys` contract.

`MultimodalPushTorchEnv` wraps ``gymnasium.make("mmf_rl/MultimodalPush-v0")`` (so its time limit
is the registered one) in a small `EnvBase` subclass rather than `GymWrapper`: the contract's
nested keys, channels-first uint8 images, float32 vectors and presence flags would otherwise take
a rename, a permute, a dtype cast and a custom transform on top of the wrapper.

Per step (single frame; `ForecastTransform` builds the history window):

=================================  ===================  =============================================
key                                spec                 meaning
=================================  ===================  =============================================
``("obs", "image")``               uint8 ``[3, h, w]``  RGB frame, channels first (record.py's
                                                        ``observation.images.front``)
``("obs", "force")``               float32 ``[6]``      gripper->object wrench (``observation.force``)
``("obs", "proprio")``             float32 ``[17]``     proprioception (``observation.state``)
``("present", m)``                 bool ``[]``          always True here; `ModalityDropout` clears it
``"object_pose"``                  float32 ``[7]``      object position + quaternion (the target's
                                                        source feature, ``observation.object_pose``)
``"goal"``                         float32 ``[3]``      goal position (``observation.goal``)
``"reward"``                       float32 ``[1]``      minus the planar object->goal distance, metres
``"terminated"``                   bool ``[1]``         FetchPush success (object within 5 cm of goal)
``"truncated"``                    bool ``[1]``         the registered time limit (50 steps)
=================================  ===================  =============================================

The action is FetchPush's ``[dx, dy, dz, gripper]`` in ``[-1, 1]``. Batch it with `SerialEnv` or
`ParallelEnv` (``mp_start_method="spawn"``): each process selects its own offscreen GL backend
when it imports `mmf_rl.envs.push`. `close()` frees the env's GL context.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from mmf_rl import keys
from mmf_rl.envs import ENV_ID  # importing the package registers it with gymnasium
from mmf_rl.envs.push import FORCE_NAMES, GOAL_NAMES, OBJECT_POSE_NAMES, PROPRIO_NAMES
from mmf_rl.envs.scripted import MIN_START_DISTANCE

MODALITIES = ("image", "force", "proprio")
OBJECT_POSE = "object_pose"
GOAL = "goal"


def push_observation_spec(image_size: int) -> Composite:
    """The spec of `MultimodalPushTorchEnv`'s observation (one env)."""
    return Composite(
        {
            keys.OBS: Composite(
                image=Bounded(0, 255, (3, image_size, image_size), dtype=torch.uint8),
                force=Unbounded((len(FORCE_NAMES),), dtype=torch.float32),
                proprio=Unbounded((len(PROPRIO_NAMES),), dtype=torch.float32),
            ),
            keys.PRESENT: Composite({m: Categorical(2, (), dtype=torch.bool) for m in MODALITIES}),
            OBJECT_POSE: Unbounded((len(OBJECT_POSE_NAMES),), dtype=torch.float32),
            GOAL: Unbounded((len(GOAL_NAMES),), dtype=torch.float32),
        }
    )


def push_action_spec() -> Bounded:
    """FetchPush's action ``[dx, dy, dz, gripper]`` in ``[-1, 1]``."""
    return Bounded(-1.0, 1.0, (4,), dtype=torch.float32)


def push_observation(obs: dict[str, np.ndarray]) -> TensorDict:
    """`MultimodalPushEnv`'s observation dict as `MultimodalPushTorchEnv` emits it (every sensor
    present): what a TorchRL policy reads, for code that steps the gymnasium env itself."""
    return TensorDict(
        {
            keys.OBS: {
                # HWC -> CHW, copied: torch must own the frame, the renderer reuses its buffer.
                "image": torch.from_numpy(np.ascontiguousarray(obs["image"].transpose(2, 0, 1))),
                "force": torch.as_tensor(obs["force"], dtype=torch.float32),
                "proprio": torch.as_tensor(obs["proprio"], dtype=torch.float32),
            },
            keys.PRESENT: {m: torch.ones((), dtype=torch.bool) for m in MODALITIES},
            OBJECT_POSE: torch.as_tensor(obs["object_pose"], dtype=torch.float32),
            GOAL: torch.as_tensor(obs["desired_goal"], dtype=torch.float32),
        },
        batch_size=[],
    )


class MultimodalPushTorchEnv(EnvBase):
    """`MultimodalPushEnv` as a TorchRL env emitting ``("obs", m)`` and ``("present", m)``.

    Args:
        image_size (int, optional): side of the square RGB image, pixels. Defaults to ``64``.
        camera (str, optional): a camera `MultimodalPushEnv` accepts (``"front"``, the default, is
            what `mmf-rl record` uses).
        max_episode_steps (int, optional): time limit; ``None`` keeps the registered 50 steps.
        min_start_distance (float, optional): resets are redrawn until the object starts at least
            this far (metres, planar) from the goal, as in the recorded data
            (`mmf_rl.envs.scripted.reset_for_push`); 0 accepts FetchPush's own draws, some of which
            start already solved.

    Raises:
        ValueError: an ``image_size`` below 8 or an unknown ``camera`` (from `MultimodalPushEnv`).

    Examples:
        >>> from mmf_rl.envs import MultimodalPushTorchEnv
        >>> env = MultimodalPushTorchEnv(image_size=32)
        >>> rollout = env.rollout(3)  # random actions
        >>> rollout["next", "obs", "image"].shape, rollout["next", "obs", "force"].shape
        (torch.Size([3, 3, 32, 32]), torch.Size([3, 6]))
        >>> rollout["next", "present", "image"]
        tensor([True, True, True])
        >>> env.close()
    """

    def __init__(
        self,
        image_size: int = 64,
        camera: str = "front",
        max_episode_steps: int | None = None,
        min_start_distance: float = MIN_START_DISTANCE,
    ):
        super().__init__(device="cpu", batch_size=torch.Size([]))
        make_kwargs = {} if max_episode_steps is None else {"max_episode_steps": max_episode_steps}
        self._env = gymnasium.make(ENV_ID, image_size=image_size, camera=camera, **make_kwargs)
        self.is_closed = False  # EnvBase starts "closed"; `close` must free this env's GL context
        self.image_size = image_size
        self.min_start_distance = min_start_distance
        self._next_seed: int | None = None

        self.observation_spec = push_observation_spec(image_size)
        self.action_spec = push_action_spec()
        self.reward_spec = Unbounded((1,), dtype=torch.float32)
        self.done_spec = Composite(
            done=Categorical(2, (1,), dtype=torch.bool),
            terminated=Categorical(2, (1,), dtype=torch.bool),
            truncated=Categorical(2, (1,), dtype=torch.bool),
        )

    @staticmethod
    def _planar_distance(obs: dict[str, np.ndarray]) -> float:
        return float(np.linalg.norm(obs["object_pose"][:2] - obs["desired_goal"][:2]))

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        seed, self._next_seed = self._next_seed, None
        obs, _ = self._env.reset(seed=seed)
        # Redraw (from the env's own seeded generator) until the episode takes a push to succeed.
        while self._planar_distance(obs) < self.min_start_distance:
            obs, _ = self._env.reset()
        out = push_observation(obs)
        false = torch.zeros(1, dtype=torch.bool)
        out.update({"done": false, "terminated": false.clone(), "truncated": false.clone()})
        return out

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy().astype(np.float64)
        obs, _, terminated, truncated, info = self._env.step(action)
        # FetchPush's own success test (3-D distance under its 5 cm threshold) ends the episode.
        terminated = bool(terminated or info.get("is_success", 0.0) > 0.5)
        out = push_observation(obs)
        out.update(
            {
                "reward": torch.tensor([-self._planar_distance(obs)], dtype=torch.float32),
                "terminated": torch.tensor([terminated]),
                "truncated": torch.tensor([bool(truncated)]),
                "done": torch.tensor([terminated or bool(truncated)]),
            }
        )
        return out

    def _set_seed(self, seed: int | None) -> None:
        # Applied at the next reset, which is where gymnasium seeds the goal and object sampling.
        self._next_seed = seed

    def close(self, *, raise_if_closed: bool = True) -> None:
        if not self.is_closed:
            self._env.close()
        super().close(raise_if_closed=raise_if_closed)
