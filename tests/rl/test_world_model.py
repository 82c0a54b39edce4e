"""`WorldModel`: forecasts and their spread in the target's units."""

import json
import logging
import re
import shutil

import pytest
import torch

from mmf_rl import keys
from mmf_rl.rl import WorldModel
from tests.conftest import assert_forecast_under_actions_is_one_forward_per_candidate

CALIBRATION_FACTOR = 2.5


def random_actions(world_model, candidates: int, seed: int = 0) -> torch.Tensor:
    shape = (1, candidates, world_model.action_steps, world_model.action_dim)
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_forecast_distribution_is_the_calibrated_decoder_in_target_units(push_world_model, push_history_env):
    window = push_history_env.reset().get(keys.HISTORY).unsqueeze(0)
    actions = random_actions(push_world_model, 3)
    encoded = push_world_model.encode(window)
    _, as_trained = push_world_model.forecast_distribution(*encoded, actions)
    # The training run calibrated the checkpoint; its factors scaled up must scale the spread up.
    calibration = push_world_model.model.scale_calibration
    saved = calibration.factors.clone()
    calibration.factors.mul_(CALIBRATION_FACTOR)
    try:
        loc, scale = push_world_model.forecast_distribution(*encoded, actions)
        normalized_actions = push_world_model.normalizer.normalize(keys.FUTURE_ACTION, actions).masked_fill(
            push_world_model.constant_action_dims, 0.0
        )
        normalized_loc, normalized_scale = assert_forecast_under_actions_is_one_forward_per_candidate(
            push_world_model.model, window, normalized_actions
        )
    finally:
        calibration.factors.copy_(saved)
    stats = push_world_model.normalizer.stats
    # By hand: the location is shifted back by the target's mean, the spread only scaled by its std.
    torch.testing.assert_close(loc, normalized_loc * stats["target/std"] + stats["target/mean"])
    torch.testing.assert_close(scale, normalized_scale * stats["target/std"])
    torch.testing.assert_close(scale, CALIBRATION_FACTOR * as_trained)
    assert torch.equal(push_world_model.forecast(*encoded, actions), loc)


def test_a_window_without_sensors_forecasts_the_marginal_mean_and_spread(push_world_model, push_history_env):
    window = push_history_env.reset().get(keys.HISTORY).unsqueeze(0)
    for spec in push_world_model.model.modalities:
        window.set(spec.present_key, torch.zeros_like(window.get(spec.present_key)))
    loc, scale = push_world_model.forecast_distribution(
        *push_world_model.encode(window), random_actions(push_world_model, 2)
    )
    stats = push_world_model.normalizer.stats
    assert torch.equal(loc, stats["target/mean"].expand_as(loc))
    assert torch.equal(scale, stats["target/std"].expand_as(scale))


def test_a_checkpoint_of_a_forecaster_without_actions_is_refused_by_path(push_forecaster_run):
    path = push_forecaster_run / "checkpoints"
    with pytest.raises(ValueError, match=re.escape(f"{path}: WorldModel needs an action-conditioned")):
        WorldModel.from_checkpoint(path)


def test_stats_without_the_action_statistics_are_named(push_world_model):
    stats = dict(push_world_model.normalizer.stats)
    del stats[f"{keys.FUTURE_ACTION}/mean"], stats[f"{keys.FUTURE_ACTION}/std"]
    with pytest.raises(KeyError, match=r"WorldModel: normalisation stats lack \['future_action/mean'"):
        WorldModel(push_world_model.model, stats)


def retrained_with_partial_windows(run, directory):
    """A copy of ``run``'s checkpoints whose data config says it was trained with
    ``data.partial_windows=true`` (the weights do not depend on it)."""
    copied = shutil.copytree(run / "checkpoints", directory / "checkpoints")
    for meta_file in copied.glob("*/meta.json"):
        meta = json.loads(meta_file.read_text())
        meta["config"]["data"]["partial_windows"] = True
        meta_file.write_text(json.dumps(meta))
    return copied


def test_the_history_window_counts_presence_as_the_run_was_trained(
    push_world_model, push_world_model_run, push_history_env, tmp_path, caplog
):
    partial = retrained_with_partial_windows(push_world_model_run, tmp_path)
    with caplog.at_level(logging.WARNING, logger="mmf_rl.rl"):
        per_step = WorldModel.from_checkpoint(partial)
    assert not caplog.records
    history = per_step.history_window()
    assert per_step.per_step_presence and history.per_step_presence
    # It plans on the windows it writes: a camera lost at the last step stays present, masked there.
    window = push_history_env.reset().get(keys.HISTORY).unsqueeze(0)
    steps = torch.ones(1, per_step.model.config.history, dtype=torch.bool)
    steps[:, -1] = False
    for spec in per_step.modalities:
        if spec.kind != "vector":
            window.set(
                keys.present_steps_key(spec.name), steps if spec.name == "image" else torch.ones_like(steps)
            )
    tokens, present, valid = per_step.encode(window)
    assert valid.all() and present.any() and tokens.isfinite().all()
    assert not torch.equal(tokens, push_world_model.encode(window.exclude(keys.PRESENT_STEPS))[0])
    assert not push_world_model.per_step_presence and not push_world_model.history_window().per_step_presence
    with caplog.at_level(logging.WARNING, logger="mmf_rl.rl"):
        overridden = WorldModel.from_checkpoint(partial, per_step_presence=False)
    assert not overridden.history_window().per_step_presence
    (record,) = caplog.records
    assert "per_step_presence=False" in record.getMessage()
    assert "data.partial_windows=True" in record.getMessage()
