"""Model-predictive control with a world model: the cross-entropy method over whole action
sequences, vectorised over candidates and envs.

Why not only torchrl's `CEMPlanner`: it scores candidates by rolling a model-based env forward
one step at a time, so a forecaster that predicts all T steps in one decode would be decoded T
times per candidate batch (and re-encoded, unless the env caches tokens, as
`ForecasterWorldModelEnv` does). Here each CEM iteration is one decoder pass over all candidates
of all envs (`benchmarks/mpc_push.py` compares the two; its results are in docs/results.md).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded

from mmf_rl import keys
from mmf_rl.rl.ensemble_world_model import EnsembleWorldModel
from mmf_rl.rl.world_model import WorldModel

IS_INIT = "is_init"  # torchrl's InitTracker flag: the first step of an episode
# The CEM's default sizes, the push MPC's (`PushMPCAgent`, `benchmarks/mpc_push.py`): smaller ones
# (128 x 4, 16 elites) ran out of time on more pushes, most often without the force sensor.
NUM_CANDIDATES, NUM_ITERATIONS, NUM_ELITES = 256, 6, 32

Objective = Callable[..., torch.Tensor]
# An objective's attribute: when true, it is called with ``forecast_scale=`` as well (see
# `SequenceCEMPlanner`); objectives without it keep the three-argument call.
USES_FORECAST_SCALE = "uses_forecast_scale"


def forecast_and_score(
    world_model: WorldModel | EnsembleWorldModel,
    objective: Objective,
    encoded: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    actions: torch.Tensor,
    context: TensorDictBase,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The forecast ``[n, N, T, D]`` (on the CPU) of raw action sequences ``[n, N, S, A]`` from encoded
    histories (the world model's ``encode``) and the objective's rewards ``[n, N, T]``; the forecast's
    standard deviation is computed and passed (``forecast_scale=``) only to an objective that asks
    for it."""
    if not getattr(objective, USES_FORECAST_SCALE, False):
        forecast = world_model.forecast(*encoded, actions).cpu()
        return forecast, objective(forecast, actions, context)
    forecast, scale = world_model.forecast_distribution(*encoded, actions)
    forecast = forecast.cpu()
    return forecast, objective(forecast, actions, context, forecast_scale=scale.cpu())


class SequenceCEMPlanner(TensorDictModuleBase):
    """A TorchRL policy: reads ``"history"`` (`mmf_rl.rl.HistoryWindow`) and the objective's
    context keys, writes ``"action"``.

    Every call (one control step, for every env of the batch): encode each env's history once;
    then ``num_iterations`` times sample ``num_candidates`` action sequences of the world model's
    ``S`` steps from a per-env diagonal Gaussian (clipped to ``action_spec``; the current mean is
    always one of them), forecast all of them in one decode, score them with ``objective``
    (rewards ``[n, N, T]`` summed over the horizon) and refit the Gaussian to the
    ``num_elites`` best. The first action of the final mean is applied. The mean is kept and
    shifted by one step to start the next call (warm start), except for envs whose ``"is_init"``
    flag (`torchrl.envs.InitTracker`) says an episode just began.

    The Gaussian lives in the world model's normalised action frame (the training data's action
    mean and std): sampling starts around what the data did, with its spread, and an action
    dim the data never varied (e.g. FetchPush's finger command) stays where the data kept it —
    the model has no idea what changing it would do.

    Args:
        world_model (WorldModel | EnsembleWorldModel): the world model (an ensemble's
            ``forecast_scale`` is the members' disagreement).
        objective (Objective): ``(forecast [n, N, T, D], actions [n, N, S, A], context) -> rewards [n, N, T]``
            with an ``in_keys`` attribute naming the context keys it reads. An objective that also scores the
            forecast's uncertainty sets ``uses_forecast_scale = True``; it is then called with
            ``forecast_scale=`` the forecast's standard deviation ``[n, N, T, D]`` in target units
            (`WorldModel.forecast_distribution`, from the same decode). An objective without the attribute (or
            with it false) is called with the three arguments alone, so a user's objective needs nothing more.
        action_spec (Bounded): the env's bounded action spec (``[A]``; a batched env's ``[*batch, A]``
            repeats one env's bounds).

    Keyword Args:
        num_candidates (int, optional): action sequences sampled per iteration. Defaults to ``256``.
        num_iterations (int, optional): refits of the sampling distribution. Defaults to ``6``.
        num_elites (int, optional): the best candidates it is refitted to. Defaults to ``32``.
        init_std (float, optional): standard deviation of the first sampling distribution, in units of
            the training data's action std. Defaults to ``1.0``.
        min_std (float, optional): floor of the refitted standard deviation (same units), so sampling
            never collapses. Defaults to ``0.05``.
        seed (int, optional): seed of the planner's own generator. Defaults to ``0``.

    Raises:
        ValueError: not ``1 <= num_elites <= num_candidates``, ``num_iterations < 1``, or an
            ``action_spec`` whose last dim is not the world model's action dim.

    Examples:
        >>> import torch
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> proprio = ModalitySpec("proprio", "sequence", (17,))
        >>> sizes = dict(history=4, horizon=5, d_model=16, d_latent=4, num_heads=2)
        >>> sizes.update(action_dim=4, action_steps=5)  # the push env's actions over the 5 steps
        >>> model = MultimodalForecaster(ForecasterConfig([force, proprio], **sizes))  # untrained world model
        >>> stats = {  # its training run's normalisation statistics (a checkpoint's tensors)
        ...     "force/mean": torch.zeros(6), "force/std": torch.ones(6),
        ...     "proprio/mean": torch.zeros(17), "proprio/std": torch.ones(17),
        ...     "target/mean": torch.zeros(2), "target/std": torch.ones(2),
        ...     "future_action/mean": torch.zeros(4), "future_action/std": torch.ones(4),
        ... }
        >>> from torchrl.envs import InitTracker, TransformedEnv, Compose
        >>> from mmf_rl.envs import MultimodalPushTorchEnv
        >>> from mmf_rl.rl import PushObjective, SequenceCEMPlanner, WorldModel
        >>> world_model = WorldModel(model, stats)
        >>> env = TransformedEnv(
        ...     MultimodalPushTorchEnv(image_size=16), Compose(InitTracker(), world_model.history_window())
        ... )
        >>> sizes = dict(num_candidates=32, num_iterations=2, num_elites=4)
        >>> planner = SequenceCEMPlanner(world_model, PushObjective(), env.action_spec, **sizes)
        >>> rollout = env.rollout(2, planner)  # a CEM decision per step, warm-started from the last
        >>> rollout["action"].shape, bool(rollout["action"].abs().max() <= 1)
        (torch.Size([2, 4]), True)
        >>> env.close()
    """

    def __init__(
        self,
        world_model: WorldModel | EnsembleWorldModel,
        objective: Objective,
        action_spec: Bounded,
        *,
        num_candidates: int = NUM_CANDIDATES,
        num_iterations: int = NUM_ITERATIONS,
        num_elites: int = NUM_ELITES,
        init_std: float = 1.0,
        min_std: float = 0.05,
        seed: int = 0,
    ):
        super().__init__()
        if not 1 <= num_elites <= num_candidates:
            raise ValueError(
                f"SequenceCEMPlanner: need 1 <= num_elites ({num_elites}) <= num_candidates "
                f"({num_candidates})"
            )
        if num_iterations < 1:
            raise ValueError(f"SequenceCEMPlanner: num_iterations must be >= 1, found {num_iterations}")
        if not action_spec.shape or action_spec.shape[-1] != world_model.action_dim:
            raise ValueError(
                f"SequenceCEMPlanner: the env's action spec has shape {list(action_spec.shape)} but the "
                f"world model was trained on actions of {world_model.action_dim} dims"
            )
        self.world_model, self.objective = world_model, objective
        # A batched env's spec repeats one env's bounds per row.
        dim = world_model.action_dim
        self.low = action_spec.space.low.float().reshape(-1, dim)[0]
        self.high = action_spec.space.high.float().reshape(-1, dim)[0]
        stats = world_model.normalizer.stats
        self.center = stats[f"{keys.FUTURE_ACTION}/mean"].cpu()
        self.spread = stats[f"{keys.FUTURE_ACTION}/std"].cpu()
        self.num_candidates, self.num_iterations, self.num_elites = num_candidates, num_iterations, num_elites
        self.init_std, self.min_std = init_std, min_std
        self.generator = torch.Generator().manual_seed(seed)
        self.in_keys = [keys.HISTORY, *objective.in_keys]
        self.out_keys = ["action"]
        self._mean: torch.Tensor | None = None  # [n, S, A] normalised, warm start

    def _raw(self, normalized: torch.Tensor) -> torch.Tensor:
        return (self.center + self.spread * normalized).clamp(self.low, self.high)

    def _initial_mean(self, tensordict: TensorDictBase, n: int) -> torch.Tensor:
        steps, dim = self.world_model.action_steps, self.world_model.action_dim
        fresh = torch.zeros(n, steps, dim)
        if self._mean is None or self._mean.shape[0] != n:
            return fresh
        shifted = torch.cat([self._mean[:, 1:], self._mean[:, -1:]], dim=1)
        init = tensordict.get(IS_INIT, None)
        if init is None:
            return shifted
        restart = init.reshape(n, -1).any(-1)
        return torch.where(restart[:, None, None], fresh, shifted)

    @torch.no_grad()
    def plan(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The CEM's final mean sequences for the envs of ``tensordict``.

        Args:
            tensordict (TensorDictBase): the env's output, with ``"history"`` and the objective's keys.

        Returns:
            ``[*batch, S, A]`` raw actions.

        Raises:
            KeyError: no ``"history"`` (the env lacks the world model's `HistoryWindow`).
        """
        if keys.HISTORY not in tensordict.keys():
            raise KeyError(
                f"SequenceCEMPlanner reads {keys.HISTORY!r}, which the env does not write: append the world "
                "model's window to the env (TransformedEnv(env, world_model.history_window()))"
            )
        batch = tensordict.batch_size
        n = batch.numel()
        window = tensordict.get(keys.HISTORY).reshape(n)
        context = tensordict.select(*self.objective.in_keys).reshape(n)
        encoded = self.world_model.encode(window)
        mean = self._initial_mean(tensordict, n)
        std = torch.full_like(mean, self.init_std)
        for _ in range(self.num_iterations):
            noise = torch.randn(n, self.num_candidates, *mean.shape[1:], generator=self.generator)
            noise[:, 0] = 0.0  # the current mean competes too
            actions = self._raw(mean[:, None] + std[:, None] * noise)
            _, rewards = forecast_and_score(self.world_model, self.objective, encoded, actions, context)
            returns = rewards.sum(-1)  # [n, N]
            elite = returns.topk(self.num_elites, dim=1).indices
            elites = actions.gather(1, elite[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
            elites = (elites - self.center) / self.spread  # clipped values, back in the sampling frame
            mean = elites.mean(1)
            std = elites.std(1, correction=0).clamp_min(self.min_std)
        self._mean = mean
        return self._raw(mean).reshape(*batch, *mean.shape[1:])

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write ``"action"``: the first action of :meth:`plan`'s sequences.

        Args:
            tensordict (TensorDictBase): the env's output.

        Returns:
            ``tensordict``.
        """
        tensordict.set("action", self.plan(tensordict)[..., 0, :])
        return tensordict
