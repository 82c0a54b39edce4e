"""The constant-velocity baseline on hand-made straight and turning trajectories."""

import math

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import build_model
from mmf_rl.models.baselines import ConstantVelocity

HISTORY, HORIZON = 8, 12
TRAJECTORY = ModalitySpec("trajectory", "sequence", (4,))


def _model(**settings) -> ConstantVelocity:
    return build_model({"name": "constant_velocity", **settings}, [TRAJECTORY], HISTORY, HORIZON, 2).eval()


def _batch(past: torch.Tensor) -> TensorDict:
    n = past.shape[0]
    return TensorDict(
        {
            TRAJECTORY.obs_key: torch.zeros(n, HISTORY, 4),
            TRAJECTORY.present_key: torch.ones(n, dtype=torch.bool),
            keys.TARGET_PAST: past,
        },
        batch_size=[n],
    )


def _circle(steps: int, radius: float = 2.0, turn: float = 0.2) -> torch.Tensor:
    """``[steps, 2]`` positions on a circle, one ``turn`` (radians) per step, ending at the origin."""
    angles = torch.arange(steps, dtype=torch.float32) * turn
    points = torch.stack([radius * angles.sin(), radius * (1 - angles.cos())], -1)
    return points - points[HISTORY - 1]


def test_a_straight_walk_is_forecast_exactly_and_every_sample_equals_it():
    line = torch.arange(-(HISTORY - 1), HORIZON + 1, dtype=torch.float32)[:, None] * torch.tensor([0.5, -0.2])
    model = _model()
    batch = _batch(line[None, :HISTORY])
    out = model(batch.clone())
    torch.testing.assert_close(out.get(keys.FORECAST_LOC)[0], line[HISTORY:])
    samples = model.sample(batch.clone(), 20).get(keys.FORECAST_SAMPLES)
    assert samples.shape == (1, 20, HORIZON, 2)
    assert (samples == out.get(keys.FORECAST_LOC)[:, None]).all(), "deterministic: 20 equal samples"


def test_a_turn_is_extrapolated_along_the_last_step_and_heading_noise_can_follow_it():
    circle = _circle(HISTORY + HORIZON)
    batch = _batch(circle[None, :HISTORY])
    loc = _model()(batch.clone()).get(keys.FORECAST_LOC)[0]
    step = circle[HISTORY - 1] - circle[HISTORY - 2]
    torch.testing.assert_close(loc, step * torch.arange(1, HORIZON + 1)[:, None])
    point_fde = (loc[-1] - circle[-1]).norm()
    torch.manual_seed(0)
    samples = _model(heading_noise=0.5).sample(batch.clone(), 20).get(keys.FORECAST_SAMPLES)[0]
    # Each sample keeps the speed and turns by its own angle: some bend towards the true turn.
    speeds = samples.diff(dim=1, prepend=torch.zeros(20, 1, 2)).norm(dim=-1)
    torch.testing.assert_close(speeds, torch.full((20, HORIZON), float(step.norm())))
    assert len({round(float(s[-1, 0]), 4) for s in samples}) == 20
    assert (samples[:, -1] - circle[-1]).norm(dim=-1).min() < 0.5 * point_fde


def test_heading_noise_turns_in_the_targets_units_not_in_normalised_ones():
    """With anisotropic target stds the turned samples keep their speed in metres."""
    scale = torch.tensor([0.5, 4.0])
    walk = torch.arange(-(HISTORY - 1), 1, dtype=torch.float32)[:, None] * torch.tensor([1.0, 1.0])
    torch.manual_seed(1)
    model = _model(heading_noise=math.pi / 4, target_scale=scale.tolist())
    samples = model.sample(_batch((walk / scale)[None]).clone(), 50).get(keys.FORECAST_SAMPLES)[0]
    metres = samples[:, 0] * scale
    torch.testing.assert_close(metres.norm(dim=-1), torch.full((50,), math.sqrt(2.0)))


def test_bad_settings_and_a_batch_without_the_past_are_named():
    with pytest.raises(ValueError, match="heading_noise must be >= 0"):
        _model(heading_noise=-0.1)
    with pytest.raises(ValueError, match="target_scale must be 2 positive stds"):
        _model(target_scale=[1.0])
    batch = _batch(torch.zeros(2, HISTORY, 2)).exclude(keys.TARGET_PAST)
    with pytest.raises(KeyError, match="include_target_past: true"):
        _model()(batch)
