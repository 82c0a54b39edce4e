"""`EnsembleWorldModel`: the members' mean forecast, their disagreement as its spread, and planning
with it wherever a `WorldModel` plans."""

import copy
import pickle

import pytest
import torch
from torchrl.data import Bounded
from torchrl.modules.planners import CEMPlanner

from mmf_rl import keys
from mmf_rl.rl import (
    EnsembleWorldModel,
    ForecasterWorldModelEnv,
    PushMPCAgent,
    PushObjective,
    SequenceCEMPlanner,
)
from mmf_rl.rl.agent import MPCActor
from mmf_rl.rl.cem import forecast_and_score

ACTIONS = Bounded(-1.0, 1.0, (4,))
SIZES = {"num_candidates": 16, "num_iterations": 2, "num_elites": 4}


def perturbed(world_model, seed: int, size: float = 0.1):
    """A copy of ``world_model`` with noise on every weight: a member trained differently on the
    same data config (same window, statistics and layout)."""
    other = copy.deepcopy(world_model)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in other.model.parameters():
            parameter.add_(size * torch.randn(parameter.shape, generator=generator))
    return other


def random_actions(world_model, candidates: int, seed: int = 0) -> torch.Tensor:
    shape = (1, candidates, world_model.action_steps, world_model.action_dim)
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * 2 - 1


@pytest.fixture(scope="module")
def window(push_history_env):
    return push_history_env.reset().get(keys.HISTORY).unsqueeze(0)


@pytest.fixture(scope="module")
def pair(push_world_model):
    return push_world_model, perturbed(push_world_model, seed=1)


def test_an_ensemble_of_one_forecasts_as_its_member_with_no_spread(push_world_model, window):
    ensemble = EnsembleWorldModel([push_world_model])
    actions = random_actions(push_world_model, 5)
    loc, scale = ensemble.forecast_distribution(*ensemble.encode(window), actions)
    expected = push_world_model.forecast(*push_world_model.encode(window), actions)
    assert torch.equal(loc, expected)
    assert torch.equal(ensemble.forecast(*ensemble.encode(window), actions), expected)
    assert torch.equal(scale, torch.zeros_like(expected))


def test_two_members_give_their_mean_and_half_their_difference(pair, window):
    first, second = pair
    actions = random_actions(first, 5)
    a = first.forecast(*first.encode(window), actions)
    b = second.forecast(*second.encode(window), actions)
    assert (a - b).abs().min() > 0  # the members do disagree
    ensemble = EnsembleWorldModel(pair)
    loc, scale = ensemble.forecast_distribution(*ensemble.encode(window), actions)
    torch.testing.assert_close(loc, (a + b) / 2)
    torch.testing.assert_close(scale, (a - b).abs() / 2)
    assert scale.shape == (1, 5, first.horizon, first.target_dim)


@pytest.mark.parametrize(
    "change, named",
    [
        (lambda m: setattr(m, "stride", m.stride + 1), "stride"),
        (lambda m: setattr(m, "horizon", m.horizon + 1), "horizon"),
        (lambda m: setattr(m, "per_step_presence", True), "per-step presence"),
        (lambda m: m.normalizer.stats["target/std"].mul_(1.001), "statistic 'target/std'"),
    ],
)
def test_members_that_read_another_window_are_refused_by_name(push_world_model, change, named):
    other = copy.deepcopy(push_world_model)
    change(other)
    with pytest.raises(ValueError, match=f"runs/b does not match runs/a: .*{named}"):
        EnsembleWorldModel([push_world_model, other], names=["runs/a", "runs/b"])


def test_sequence_cem_planner_plans_with_an_ensemble_reproducibly(pair, push_history_env):
    ensemble = EnsembleWorldModel(pair)
    td = push_history_env.reset()
    plans = [
        SequenceCEMPlanner(ensemble, PushObjective(uncertainty_weight=1.0), ACTIONS, seed=3, **SIZES).plan(td)
        for _ in range(2)
    ]
    assert plans[0].shape == (ensemble.action_steps, ensemble.action_dim)
    assert torch.equal(plans[0], plans[1])


def test_the_penalty_ranks_the_plans_the_members_disagree_on_lower(pair, push_history_env):
    ensemble = EnsembleWorldModel(pair)
    td = push_history_env.reset().unsqueeze(0)
    context = td.select(*PushObjective.in_keys)
    encoded = ensemble.encode(td.get(keys.HISTORY))
    actions = random_actions(ensemble, 32)
    _, disagreement = ensemble.forecast_distribution(*encoded, actions)
    spread = disagreement.norm(dim=-1).sum(-1)[0]  # [N], metres summed over the horizon
    _, plain = forecast_and_score(ensemble, PushObjective(), encoded, actions, context)
    weight = 1e6  # the penalty dominates: the ranking is the disagreement's
    _, penalised = forecast_and_score(
        ensemble, PushObjective(uncertainty_weight=weight), encoded, actions, context
    )
    torch.testing.assert_close(penalised.sum(-1)[0], plain.sum(-1)[0] - weight * spread)
    returns = penalised.sum(-1)[0]
    assert returns.argmax() == spread.argmin() and returns.argmin() == spread.argmax()


def test_the_mpc_agent_of_several_checkpoints_plans_with_their_ensemble(push_world_model_run):
    checkpoint = push_world_model_run / "checkpoints"
    agent = PushMPCAgent([checkpoint, checkpoint], image_size=32, **SIZES)
    actor = agent()
    assert isinstance(actor, MPCActor)
    assert isinstance(actor.planner.world_model, EnsembleWorldModel)
    assert len(actor.planner.world_model.members) == 2
    assert "ensemble" in str(agent)
    assert pickle.loads(pickle.dumps(agent)) == agent  # what a recording worker receives


def test_the_world_model_env_rolls_out_an_ensemble_and_penalises_its_disagreement(pair, push_history_env):
    ensemble = EnsembleWorldModel(pair)
    objective = PushObjective(uncertainty_weight=1.0)
    env = ForecasterWorldModelEnv(ensemble, objective, ACTIONS, push_history_env.observation_spec)
    real = push_history_env.reset()
    state = env.reset(real.select(keys.HISTORY, *objective.in_keys))
    action = torch.full((4,), 0.5)
    reward = env.step(state.set("action", action)).get(("next", "reward"))

    held = action.expand(ensemble.action_steps, -1)[None, None]
    encoded = ensemble.encode(real.get(keys.HISTORY).unsqueeze(0))
    forecast, disagreement = ensemble.forecast_distribution(*encoded, held)
    context = real.select(*objective.in_keys).unsqueeze(0)
    expected = objective(forecast, held, context, forecast_scale=disagreement)[0, 0, 0]
    torch.testing.assert_close(reward[0], expected)
    cem = CEMPlanner(env, planning_horizon=ensemble.action_steps, optim_steps=2, num_candidates=8, top_k=2)
    action = cem.planning(env.reset(real.select(keys.HISTORY, *objective.in_keys)))
    assert action.shape == (4,) and torch.isfinite(action).all()
