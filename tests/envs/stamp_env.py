"""A fake env with the push env's observation layout, whose every value tells which step it is."""

from __future__ import annotations

import functools

import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase, SerialEnv

from mmf_rl import keys
from tests.envs.conftest import IMAGE_SIZE

MODALITIES = ("image", "force", "proprio")
VECTOR_DIMS = {"force": 6, "proprio": 17}


class StampEnv(EnvBase):
    """The push env's observation layout, filled with a stamp of (env, episode, step).

    Every entry of ``("obs", m)`` at step ``t`` of episode ``e`` of env ``k`` holds
    ``stamp = 1000 * k + 100 * e + t + 1`` (images: ``stamp % 256``), so a window read back from a
    transform tells exactly which steps it holds.
    """

    def __init__(self, env_index: int = 0, max_steps: int = 1000):
        super().__init__(batch_size=torch.Size([]))
        self.env_index, self.max_steps = env_index, max_steps
        self.episode, self.t = -1, 0
        self.observation_spec = Composite(
            {
                keys.OBS: Composite(
                    image=Bounded(0, 255, (3, IMAGE_SIZE, IMAGE_SIZE), dtype=torch.uint8),
                    **{m: Unbounded((d,)) for m, d in VECTOR_DIMS.items()},
                ),
                keys.PRESENT: Composite({m: Categorical(2, (), dtype=torch.bool) for m in MODALITIES}),
            }
        )
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))

    def stamp(self) -> int:
        return 1000 * self.env_index + 100 * self.episode + self.t + 1

    def _observation(self) -> TensorDict:
        stamp = self.stamp()
        return TensorDict(
            {
                keys.OBS: {
                    "image": torch.full((3, IMAGE_SIZE, IMAGE_SIZE), stamp % 256, dtype=torch.uint8),
                    **{m: torch.full((d,), float(stamp)) for m, d in VECTOR_DIMS.items()},
                },
                keys.PRESENT: {m: torch.tensor(True) for m in MODALITIES},
            },
            batch_size=[],
        )

    def _reset(self, tensordict=None, **kwargs):
        self.episode, self.t = self.episode + 1, 0
        return self._observation().update(
            {"done": torch.tensor([False]), "terminated": torch.tensor([False])}
        )

    def _step(self, tensordict):
        self.t += 1
        done = torch.tensor([self.t >= self.max_steps])
        return self._observation().update(
            {"reward": torch.zeros(1), "done": done, "terminated": done.clone()}
        )

    def _set_seed(self, seed):
        pass


def stamp_envs(num_envs: int, max_steps: int = 1000) -> SerialEnv:
    return SerialEnv(num_envs, [functools.partial(StampEnv, k, max_steps) for k in range(num_envs)])
