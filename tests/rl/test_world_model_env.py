"""`ForecasterWorldModelEnv`: a trained world model as a TorchRL model-based env."""

import pytest
import torch
from torchrl.modules.planners import CEMPlanner, MPPIPlanner

from mmf_rl import keys
from mmf_rl.rl import ForecasterWorldModelEnv, PushObjective
from mmf_rl.rl.world_model_env import ACTIONS, FORECAST, STEP


@pytest.fixture
def imagined(push_world_model, push_history_env):
    objective = PushObjective()
    env = ForecasterWorldModelEnv(
        push_world_model, objective, push_history_env.action_spec, push_history_env.observation_spec
    )
    real = push_history_env.rollout(3, break_when_any_done=False)[-1].get("next")
    return env, objective, real


def test_imagined_rollout_equals_the_world_model_under_the_held_actions(push_world_model, imagined):
    env, objective, real = imagined
    state = env.reset(real.select(keys.HISTORY, *objective.in_keys))
    actions = torch.rand(push_world_model.action_steps, 4, generator=torch.Generator().manual_seed(0)) * 2 - 1
    rollout = env.rollout(
        push_world_model.action_steps,
        policy=lambda td: td.set("action", actions[int(td.get(STEP))]),
        auto_reset=False,
        tensordict=state.clone(),
    )
    assert rollout.shape == (push_world_model.action_steps,)
    assert rollout.get(("next", "done"))[-1].item() and not rollout.get(("next", "done"))[:-1].any()
    assert (rollout.get(("next", *ACTIONS))[-1] == actions).all()

    # Step k saw actions 0..k, the k-th held to the end: its forecast and reward are the model's.
    window = real.get(keys.HISTORY).unsqueeze(0)
    tokens, present, valid = push_world_model.encode(window)
    context = real.select(*objective.in_keys).unsqueeze(0)
    for k in range(push_world_model.action_steps):
        held = torch.cat(
            [actions[: k + 1], actions[k : k + 1].expand(push_world_model.action_steps - k - 1, -1)]
        )
        forecast = push_world_model.forecast(tokens, present, valid, held[None, None])
        torch.testing.assert_close(rollout.get(("next", *FORECAST))[k], forecast[0, 0, k])
        reward = objective(forecast, held[None, None], context)[0, 0, k]
        torch.testing.assert_close(rollout.get(("next", "reward"))[k, 0], reward)


@pytest.mark.parametrize("planner_cls", [CEMPlanner, MPPIPlanner])
def test_torchrl_planners_plan_in_the_world_model_env(push_world_model, imagined, planner_cls):
    env, objective, real = imagined
    state = env.reset(real.select(keys.HISTORY, *objective.in_keys))
    if planner_cls is CEMPlanner:
        planner = CEMPlanner(
            env, planning_horizon=push_world_model.action_steps, optim_steps=2, num_candidates=16, top_k=4
        )
    else:
        planner = MPPIPlanner(
            env,
            advantage_module=lambda td: td.set("advantage", td.get(("next", "reward"))),
            temperature=1.0,
            planning_horizon=push_world_model.action_steps,
            optim_steps=2,
            num_candidates=16,
            top_k=4,
        )
    action = planner.planning(state)
    assert action.shape == (4,) and torch.isfinite(action).all()


def test_reset_without_history_names_what_is_missing(imagined):
    env, objective, real = imagined
    with pytest.raises(KeyError, match="needs a real env's tensordict with 'history'.*HistoryWindow"):
        env.reset(real.select(*objective.in_keys))


def test_imagined_rewards_include_the_uncertainty_penalty(push_world_model, push_history_env, imagined):
    _, _, real = imagined
    objective = PushObjective(uncertainty_weight=1.0)
    env = ForecasterWorldModelEnv(
        push_world_model, objective, push_history_env.action_spec, push_history_env.observation_spec
    )
    state = env.reset(real.select(keys.HISTORY, *objective.in_keys))
    action = torch.full((4,), 0.5)
    reward = env.step(state.set("action", action)).get(("next", "reward"))

    held = action.expand(push_world_model.action_steps, -1)[None, None]
    encoded = push_world_model.encode(real.get(keys.HISTORY).unsqueeze(0))
    forecast, scale = push_world_model.forecast_distribution(*encoded, held)
    context = real.select(*objective.in_keys).unsqueeze(0)
    expected = objective(forecast, held, context, forecast_scale=scale)[0, 0, 0]
    torch.testing.assert_close(reward[0], expected)
    assert reward[0] < PushObjective()(forecast, held, context)[0, 0, 0]
