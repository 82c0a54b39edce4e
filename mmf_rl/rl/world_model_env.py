"""A trained world model as a TorchRL model-based env: imagined rollouts from real history.

`ForecasterWorldModelEnv` is a `torchrl.envs.model_based.ModelBasedEnvBase`, so torchrl's
planners (`CEMPlanner`, `MPPIPlanner`) and any code written for model-based envs can roll it out.
Its state starts from a real env's tensordict: the ``"history"`` window (`HistoryWindow`) and the
objective's context keys. The history is encoded once at reset and the tokens kept in the state,
so an imagined step costs one decoder pass.

An imagined step ``k`` records the action in the sequence and, since the forecaster decodes a
whole ``S``-step sequence at once, holds it for the steps not chosen yet; the step's observation
is the forecast at the forecast step holding ``k`` (``k // stride``) and its reward the
objective's reward there. After ``S`` steps (the action steps one forecast covers: ``T`` forecast
steps of ``stride`` env steps) the imagined episode is done: the model cannot see further.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.model_based import ModelBasedEnvBase
from torchrl.modules.planners import MPCPlannerBase

from mmf_rl import keys
from mmf_rl.rl.cem import Objective, forecast_and_score
from mmf_rl.rl.ensemble_world_model import EnsembleWorldModel
from mmf_rl.rl.world_model import WorldModel

IMAGINED = "imagined"
TOKENS = (IMAGINED, "tokens")  # the world model's encoding: [N, d], an ensemble's [K, N, d]
TOKEN_PRESENT = (IMAGINED, "token_present")  # [N] ([K, N]) per token slot; not the batch key ("present", m)
VALID = (IMAGINED, "valid")
ACTIONS = (IMAGINED, "actions")
STEP = (IMAGINED, "step")
FORECAST = (IMAGINED, "forecast")  # the imagined target at the current step (target units)


class ForecasterWorldModelEnv(ModelBasedEnvBase):
    """Imagined rollouts of a `WorldModel` scored by an objective (e.g. `PushObjective`).

    ``self.world_model`` is the underlying forecaster (as `ModelBasedEnvBase` names it; an
    ensemble's: its members' in a `torch.nn.ModuleList`); ``self.dynamics`` the `WorldModel` (or
    `EnsembleWorldModel`) that wraps it with its normalisation.

    Args:
        world_model (WorldModel | EnsembleWorldModel): the trained world model, or an ensemble (the
            state then holds every member's encoding, and a penalising objective gets the members'
            disagreement).
        objective (Objective): ``(forecast, actions, context) -> rewards [n, N, T]`` with ``in_keys``
            (the context keys it reads, carried unchanged through the imagined state); one that sets
            ``uses_forecast_scale`` also gets ``forecast_scale=``, as in `SequenceCEMPlanner`.
        action_spec (Bounded): one real env's action spec (``[A]``; the imagined batch is whatever the
            reset tensordict's is).
        context_spec (Composite): specs of the objective's context keys (take them from the real env's
            observation spec).

    Reset it from a real env's tensordict (a ``reset`` without ``"history"`` is a ``KeyError``);
    stepping past the ``S`` steps one forecast covers is a ``RuntimeError``.

    Raises:
        ValueError: an ``action_spec`` of another shape than the world model's actions.

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
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl.modules.planners import CEMPlanner
        >>> from mmf_rl.envs import MultimodalPushTorchEnv
        >>> from mmf_rl.rl import ForecasterWorldModelEnv, ImaginedPlanningPolicy, PushObjective, WorldModel
        >>> world_model = WorldModel(model, stats)
        >>> real_env = TransformedEnv(MultimodalPushTorchEnv(image_size=16), world_model.history_window())
        >>> objective = PushObjective()
        >>> wm_env = ForecasterWorldModelEnv(
        ...     world_model, objective, real_env.action_spec, real_env.observation_spec
        ... )
        >>> real = real_env.reset()
        >>> state = wm_env.reset(real.select("history", *objective.in_keys))  # encodes the history once
        >>> imagined = wm_env.rollout(10, tensordict=state, auto_reset=False)  # random actions
        >>> imagined["next", "reward"].shape  # done after the model's S = 5 action steps
        torch.Size([5, 1])
        >>> planner = CEMPlanner(wm_env, planning_horizon=5, optim_steps=2, num_candidates=16, top_k=4)
        >>> policy = ImaginedPlanningPolicy(planner, wm_env)  # the real env's policy
        >>> policy(real)["action"].shape
        torch.Size([4])
        >>> real_env.close()
    """

    def __init__(
        self,
        world_model: WorldModel | EnsembleWorldModel,
        objective: Objective,
        action_spec: Bounded,
        context_spec: Composite,
    ):
        if action_spec.shape != (world_model.action_dim,):
            raise ValueError(
                f"ForecasterWorldModelEnv: action_spec must be one env's, shape [{world_model.action_dim}] "
                f"(what the world model was trained on); found {list(action_spec.shape)}"
            )
        forecasters = (
            torch.nn.ModuleList([member.model for member in world_model.members])
            if isinstance(world_model, EnsembleWorldModel)
            else world_model.model
        )
        super().__init__(forecasters, device=world_model.device, batch_size=torch.Size([]))
        self.dynamics, self.objective = world_model, objective
        token_shape = world_model.token_shape
        steps, dim = world_model.action_steps, world_model.action_dim
        self.action_spec = action_spec
        # The imagined state is observed (as Dreamer's model-based env observes its latent state),
        # so every step carries it forward.
        self.observation_spec = Composite(
            {
                FORECAST: Unbounded((world_model.target_dim,), dtype=torch.float32),
                TOKENS: Unbounded(token_shape, dtype=torch.float32),
                TOKEN_PRESENT: Categorical(2, token_shape[:-1], dtype=torch.bool),
                VALID: Categorical(2, (), dtype=torch.bool),
                ACTIONS: Unbounded((steps, dim), dtype=torch.float32),
                STEP: Unbounded((1,), dtype=torch.int64),
                **{k: context_spec[k] for k in objective.in_keys},
            }
        )
        self.reward_spec = Unbounded((1,), dtype=torch.float32)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        if tensordict is None or keys.HISTORY not in tensordict.keys():
            raise KeyError(
                f"ForecasterWorldModelEnv.reset needs a real env's tensordict with {keys.HISTORY!r} (add "
                f"HistoryWindow to the real env) and the objective's keys {self.objective.in_keys}"
            )
        batch = tensordict.batch_size
        n = batch.numel()
        tokens, present, valid = self.dynamics.encode(tensordict.get(keys.HISTORY).reshape(n))
        steps, dim = self.dynamics.action_steps, self.dynamics.action_dim
        state = TensorDict(
            {
                TOKENS: tokens,
                TOKEN_PRESENT: present,
                VALID: valid,
                ACTIONS: torch.zeros(n, steps, dim),
                STEP: torch.zeros(n, 1, dtype=torch.int64),
                FORECAST: torch.zeros(n, self.dynamics.target_dim),
                "done": torch.zeros(n, 1, dtype=torch.bool),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
            batch_size=[n],
        ).reshape(batch)
        return state.update(tensordict.select(*self.objective.in_keys))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        n = batch.numel()
        flat = tensordict.reshape(n)
        step = flat.get(STEP)  # [n, 1]
        steps = self.dynamics.action_steps
        if bool((step >= steps).any()):
            raise RuntimeError(
                f"ForecasterWorldModelEnv: imagined past the model's horizon ({steps} action steps); "
                "reset from real history"
            )
        # The new action replaces this step's and, until chosen, every later step's.
        later = torch.arange(steps)[None, :, None] >= step[:, :, None]
        actions = torch.where(later, flat.get("action")[:, None, :], flat.get(ACTIONS))
        context = flat.select(*self.objective.in_keys)
        encoded = (flat.get(TOKENS), flat.get(TOKEN_PRESENT), flat.get(VALID))
        forecast, rewards = forecast_and_score(
            self.dynamics, self.objective, encoded, actions[:, None], context
        )
        rewards = rewards[:, 0]  # [n, T]
        index = step // (steps // self.dynamics.horizon)  # the forecast step of this action's frame
        reward = rewards.gather(1, index)
        predicted = forecast[:, 0].gather(1, index[:, :, None].expand(-1, -1, forecast.shape[-1]))[:, 0]
        done = step + 1 >= steps
        out = TensorDict(
            {
                TOKENS: flat.get(TOKENS),
                TOKEN_PRESENT: flat.get(TOKEN_PRESENT),
                VALID: flat.get(VALID),
                ACTIONS: actions,
                STEP: step + 1,
                FORECAST: predicted,
                "reward": reward,
                "done": done,
                "terminated": done.clone(),
            },
            batch_size=[n],
        )
        return out.update(context).reshape(batch)


class ImaginedPlanningPolicy(TensorDictModuleBase):
    """A real env's policy that plans with a torchrl planner in a `ForecasterWorldModelEnv`.

    Each call resets the world-model env from the real tensordict (``"history"`` and the
    objective's context: the history is encoded once) and asks ``planner`` (torchrl's
    `CEMPlanner`, `MPPIPlanner`, ... built on that env) for the action to take. See
    `ForecasterWorldModelEnv`'s example.

    Args:
        planner (MPCPlannerBase): a torchrl planner built on ``world_model_env``.
        world_model_env (ForecasterWorldModelEnv): the imagined env.
    """

    def __init__(self, planner: MPCPlannerBase, world_model_env: ForecasterWorldModelEnv):
        super().__init__()
        self.planner, self.world_model_env = planner, world_model_env
        self.in_keys = [keys.HISTORY, *world_model_env.objective.in_keys]
        self.out_keys = ["action"]

    @torch.no_grad()
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        state = self.world_model_env.reset(tensordict.select(*self.in_keys))
        return tensordict.set("action", self.planner.planning(state))
