"""The MPC agent as an `Actor` of the recorder: what `mmf-rl record --policy CHECKPOINT` records with.

`mmf_rl.record` steps the gymnasium env (`MultimodalPushEnv`) itself, one process per worker, and
sits below the models: it cannot load a world model. It takes a picklable factory instead,
`PushMPCAgent` (a checkpoint path and the planner's sizes), and calls it once in each worker,
which so builds its own world model and planner. Its policy is the one `benchmarks/mpc_push.py`
and `examples/mpc_push.py` play in the TorchRL env: `SequenceCEMPlanner` on the world model with
`PushObjective`, reading the `HistoryWindow` of every sensor.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from mmf_rl.envs.torchrl_env import push_action_spec, push_observation, push_observation_spec
from mmf_rl.rl.cem import IS_INIT, NUM_CANDIDATES, NUM_ELITES, NUM_ITERATIONS, Objective, SequenceCEMPlanner
from mmf_rl.rl.ensemble_world_model import EnsembleWorldModel
from mmf_rl.rl.push_objective import KEEP_OUT_WEIGHT, REACH_WEIGHT, PushObjective
from mmf_rl.rl.world_model import WorldModel


class MPCActor:
    """`SequenceCEMPlanner` driven by `MultimodalPushEnv`'s observation dicts (`mmf_rl.envs.scripted.Actor`).

    Every observation goes through the world model's `HistoryWindow` (the first of an episode
    fills the window, as after an env reset), then the planner picks the action. `reset` reseeds
    the planner from the episode's generator and restarts its warm start, so an episode depends
    only on that generator.

    Args:
        world_model (WorldModel | EnsembleWorldModel): the world model planned with.
        objective (Objective): what the planner maximises (`PushObjective`).
        image_size (int): the env's camera size (its window resizes frames to the model's).
        **planner_kwargs: `SequenceCEMPlanner`'s keyword arguments (sizes, ``seed``).
    """

    def __init__(
        self,
        world_model: WorldModel | EnsembleWorldModel,
        objective: Objective,
        image_size: int,
        **planner_kwargs,
    ):
        self.history = world_model.history_window()
        # What TransformedEnv checks when the window is appended to the env: the checkpoint's
        # modalities against the env's sensors (a clear error naming both).
        self.history.transform_observation_spec(push_observation_spec(image_size))
        self.planner = SequenceCEMPlanner(world_model, objective, push_action_spec(), **planner_kwargs)
        self._new_episode = True

    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: reseed the planner from ``rng`` and drop its warm start.

        Args:
            rng (np.random.Generator): the episode's generator.
        """
        self.planner.generator.manual_seed(int(rng.integers(2**63)))
        self._new_episode = True

    @torch.no_grad()
    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """The planner's action for this observation.

        Args:
            obs (dict[str, np.ndarray]): `MultimodalPushEnv`'s observation.

        Returns:
            A FetchPush action, float32 ``[4]``.
        """
        observation = push_observation(obs)
        # The recorder steps the gymnasium env, not a TorchRL one: the window is fed as
        # TransformedEnv feeds it at a reset and a step.
        if self._new_episode:
            observation = self.history.observe_reset(observation)
        else:
            observation = self.history.observe_step(observation)
        observation.set(IS_INIT, torch.tensor([self._new_episode]))
        self._new_episode = False
        return self.planner(observation).get("action").numpy()


@dataclass(frozen=True)
class PushMPCAgent:
    """A picklable factory of `MPCActor` on the world model at ``checkpoint`` (a run directory, its
    ``checkpoints/``, one checkpoint or a ``save_pretrained`` directory; a sequence of them: their
    `EnsembleWorldModel`): pass it as `mmf_rl.record.RecordConfig.policy`.

    Constructing it loads the checkpoint once and builds an agent, so a bad path or a model that
    is not a push world model fails here, in the caller, not in every recording worker.
    ``image_size`` is the recording's (the window resizes frames to the model's size).
    The sizes and the weights are `SequenceCEMPlanner`'s and `PushObjective`'s; their defaults are
    `benchmarks/mpc_push.py`'s.

    Args:
        checkpoint (Path | tuple[Path, ...]): the world model (a path), or an ensemble's (paths).
        image_size (int, optional): the recording's camera size. Defaults to ``64``.
        num_candidates (int, optional): `SequenceCEMPlanner`'s. Defaults to ``256``.
        num_iterations (int, optional): `SequenceCEMPlanner`'s. Defaults to ``6``.
        num_elites (int, optional): `SequenceCEMPlanner`'s. Defaults to ``32``.
        reach_weight (float, optional): `PushObjective`'s. Defaults to ``0.5``.
        uncertainty_weight (float, optional): `PushObjective`'s. Defaults to ``0``.
        keep_out_weight (float, optional): `PushObjective`'s. Defaults to ``10.0``.
    """

    checkpoint: Path | tuple[Path, ...]
    image_size: int = 64
    num_candidates: int = NUM_CANDIDATES
    num_iterations: int = NUM_ITERATIONS
    num_elites: int = NUM_ELITES
    reach_weight: float = REACH_WEIGHT
    uncertainty_weight: float = 0.0
    keep_out_weight: float = KEEP_OUT_WEIGHT

    def __post_init__(self):
        given = self.checkpoint
        several = isinstance(given, Sequence) and not isinstance(given, str | os.PathLike)
        object.__setattr__(self, "checkpoint", tuple(map(Path, given)) if several else Path(given))
        self()

    def world_model(self) -> WorldModel | EnsembleWorldModel:
        """Load the world model (or the ensemble) at ``checkpoint``."""
        if isinstance(self.checkpoint, tuple):
            return EnsembleWorldModel.from_checkpoints(self.checkpoint)
        return WorldModel.from_checkpoint(self.checkpoint)

    def __call__(self) -> MPCActor:
        return MPCActor(
            self.world_model(),
            PushObjective(
                reach_weight=self.reach_weight,
                uncertainty_weight=self.uncertainty_weight,
                keep_out_weight=self.keep_out_weight,
            ),
            self.image_size,
            num_candidates=self.num_candidates,
            num_iterations=self.num_iterations,
            num_elites=self.num_elites,
        )

    def __str__(self) -> str:
        world_model = (
            f"the ensemble of {', '.join(map(str, self.checkpoint))}"
            if isinstance(self.checkpoint, tuple)
            else f"the world model {self.checkpoint}"
        )
        return (
            f"MPC on {world_model} ({self.num_candidates} candidates x "
            f"{self.num_iterations} iterations, {self.num_elites} elites)"
        )
