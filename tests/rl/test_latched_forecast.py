from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from mmf_rl import keys
from mmf_rl.checkpoint import META_FILE
from mmf_rl.rl.latched_forecast import LatchedForecastTransform
from mmf_rl.rl.transforms import ForecastTransform
from tests.envs.stamp_env import stamp_envs
from tests.rl.conftest import RECORDED_ENVS
from tests.rl.test_transforms import HISTORY, HORIZON, PUSH_SPECS, TARGET_DIM, write_checkpoint

GRIPPER = {"feature": "observation.state", "dims": [0, 1]}


def target_checkpoint(directory, target: dict, stride: int = 1):
    """A checkpoint whose data config forecasts ``target`` (its frame: relative, relative_to)."""
    checkpoint = write_checkpoint(directory, PUSH_SPECS, stride=stride)
    meta_file = next(checkpoint.glob(f"step_*/{META_FILE}"))
    meta = json.loads(meta_file.read_text())
    meta["config"]["data"]["target"] = {"feature": "observation.object_pose", "dims": [0, 1], **target}
    meta["config"]["data"]["modalities"] = {
        "image": "observation.images.front",
        "force": "observation.force",
        "proprio": "observation.state",
    }
    meta_file.write_text(json.dumps(meta))
    return checkpoint


@pytest.fixture(scope="module")
def absolute_checkpoint(tmp_path_factory):
    return target_checkpoint(tmp_path_factory.mktemp("absolute"), {})


def camera_outages(steps: list[TensorDict], outages: dict[int, range]) -> list[TensorDict]:
    """``steps`` with env ``e``'s camera flagged absent over ``outages[e]``."""
    out = []
    for t, step in enumerate(steps):
        step = step[: len(outages)].clone()
        for env, steps_off in outages.items():
            if t in steps_off:
                step[keys.present_key("image")][env] = False
        out.append(step)
    return out


def replay(transform, steps: list[TensorDict]) -> list[TensorDict]:
    outputs = [transform.observe_reset(steps[0].clone())]
    return outputs + [transform.observe_step(step.clone()) for step in steps[1:]]


def expected_ages(steps: list[TensorDict], env: int) -> list[int]:
    """Env steps since the camera last filled the window (every one of its ``HISTORY`` steps;
    before the first step, the reset's frame fills it)."""
    present = [bool(s[keys.present_key("image")][env]) for s in steps]
    ages, last = [], None
    for t in range(len(steps)):
        window = [present[max(0, t - i)] for i in range(HISTORY)]
        last = t if all(window) else last
        ages.append(0 if last is None else t - last)
    return ages


def advanced_by_hand(loc: torch.Tensor, age: int, stride: int = 1) -> torch.Tensor:
    """The forecast ``loc`` ``[T, D]`` made ``age`` env steps ago, served for now (absolute target)."""
    shift = age // stride
    return torch.stack([loc[min(shift + k, HORIZON) - 1] for k in range(1, HORIZON + 1)])


def scale_by_hand(scale: torch.Tensor, age: int, stride: int = 1) -> torch.Tensor:
    """The latched ``scale`` ``[T, D]`` served ``age`` env steps later: each forecast step past the
    horizon adds the variance the forecast gained over its last step."""
    growth = (scale[-1] ** 2 - scale[-2] ** 2).clamp(min=0)
    shift, rows = age // stride, []
    for k in range(1, HORIZON + 1):
        past = max(0, shift + k - HORIZON)
        rows.append((scale[min(shift + k, HORIZON) - 1] ** 2 + past * growth).sqrt())
    return torch.stack(rows)


def test_latch_holds_and_ages_through_a_camera_outage_and_relatches_when_it_returns(
    recorded_steps,
    absolute_checkpoint,
):
    steps = camera_outages(recorded_steps, {0: range(6, 18)})
    plain = replay(ForecastTransform.from_checkpoint(absolute_checkpoint), steps)
    latched = replay(LatchedForecastTransform.from_checkpoint(absolute_checkpoint, rule="latched"), steps)
    ages = expected_ages(steps, 0)
    assert max(ages) > HORIZON, "the outage outlasts the horizon: the last step is held"
    for t, (fresh, served) in enumerate(zip(plain, latched, strict=True)):
        age = ages[t]
        assert served[keys.FORECAST_AGE].tolist() == [float(age)], f"step {t}"
        latch = plain[t - age]
        expected_loc = advanced_by_hand(latch[keys.FORECAST_LOC][0], age)
        expected_scale = scale_by_hand(latch[keys.FORECAST_SCALE][0], age)
        for key, expected in ((keys.FORECAST_LOC, expected_loc), (keys.FORECAST_SCALE, expected_scale)):
            torch.testing.assert_close(
                served[key][0], expected, msg=lambda m, t=t, k=key: f"step {t} {k}: {m}"
            )
        if age == 0:
            torch.testing.assert_close(served[keys.FORECAST_LOC], fresh[keys.FORECAST_LOC])
    back = 18 + HISTORY - 1  # the camera fills the window again
    assert ages[back - 1] > 0 and ages[back] == 0, "re-latched once the camera is back"


def test_with_per_step_presence_the_latch_refreshes_whenever_the_camera_holds_the_newest_step(
    recorded_steps, absolute_checkpoint
):
    steps = camera_outages(recorded_steps, {0: [*range(4, 7), *range(9, 12)]})  # two bursts
    options = {"per_step_presence": True}
    plain = replay(ForecastTransform.from_checkpoint(absolute_checkpoint, **options), steps)
    latched = replay(
        LatchedForecastTransform.from_checkpoint(absolute_checkpoint, rule="latched", **options), steps
    )
    present = [bool(s[keys.present_key("image")][0]) for s in steps]
    last_present = [max(u for u in range(t + 1) if present[u]) for t in range(len(steps))]
    for t, served in enumerate(latched):
        age = t - last_present[t]
        assert served[keys.FORECAST_AGE].tolist() == [float(age)], f"step {t}"
        expected = advanced_by_hand(plain[t - age][keys.FORECAST_LOC][0], age)
        torch.testing.assert_close(
            served[keys.FORECAST_LOC][0], expected, msg=lambda m, t=t: f"step {t}: {m}"
        )
    # Between the bursts the camera never fills the window, yet each of its frames refreshes the latch.
    assert [latched[t][keys.FORECAST_AGE].item() for t in (7, 8, 12)] == [0.0, 0.0, 0.0]
    whole_window = replay(
        LatchedForecastTransform.from_checkpoint(absolute_checkpoint, rule="latched"), steps
    )
    assert whole_window[8][keys.FORECAST_AGE].item() == 5.0  # the window last filled at step 3


def test_each_env_of_a_batch_keeps_its_own_latch_and_a_reset_clears_it(
    recorded_steps,
    absolute_checkpoint,
):
    """Three envs, three outages; env 1 is reset mid-outage (its camera still off)."""
    outages = {0: range(5, 12), 1: range(8, 40), 2: range(14, 20)}
    steps = camera_outages(recorded_steps, outages)
    transform = LatchedForecastTransform.from_checkpoint(absolute_checkpoint, rule="latched")
    outputs = replay(transform, steps[:15])
    for env in range(RECORDED_ENVS):
        got = [o[keys.FORECAST_AGE][env].item() for o in outputs]
        assert got == expected_ages(steps[:15], env), f"env {env}"
    reset = TensorDict({"_reset": torch.tensor([[False], [True], [False]])}, batch_size=[RECORDED_ENVS])
    # A partial reset, as a TransformedEnv hands it to its transforms.
    after = transform._reset(reset, steps[15].clone())  # noqa: SLF001
    assert after[keys.FORECAST_AGE].tolist() == [0.0, 0.0, 1.0], (
        "only env 1's latch is cleared; env 2 did not step"
    )
    fresh = ForecastTransform.from_checkpoint(absolute_checkpoint)
    replay(fresh, steps[:15])
    expected = fresh._reset(reset, steps[15].clone())  # noqa: SLF001
    # No camera since its reset: env 1 has no latch, so it is served the fresh forecast.
    torch.testing.assert_close(after[keys.FORECAST_LOC][1], expected[keys.FORECAST_LOC][1])
    following = transform.observe_step(steps[16].clone())
    assert following[keys.FORECAST_AGE].tolist() == [0.0, 0.0, 2.0]


def synthetic_latch(transform: LatchedForecastTransform, ages: list[int]) -> torch.Tensor:
    """Give every env of ``transform`` a latched forecast ``[n, T, D]`` of distinct values and ``ages``."""
    n = len(ages)
    latched = torch.arange(n * HORIZON * TARGET_DIM, dtype=torch.float32).reshape(n, HORIZON, TARGET_DIM)
    latched = latched.pow(1.5)  # not linear in the step: a wrong shift cannot pass by accident
    transform._latched_loc.copy_(latched)  # noqa: SLF001
    transform._latched_scale.copy_(latched.sqrt() + 1)  # noqa: SLF001 - growing with the step
    transform._age.copy_(torch.tensor(ages))  # noqa: SLF001
    transform._has_latch.fill_(True)  # noqa: SLF001
    return latched


@pytest.mark.parametrize("stride", [1, 2])
def test_a_relative_forecast_is_rebased_to_the_current_step(recorded_steps, tmp_path, stride):
    """A displacement from the latch step, advanced by ``s`` forecast steps, is the displacement from
    the latched forecast's own position at ``s``: ``L[s + k] - L[s]`` (``L[0] = 0``, held past T);
    past T the held step's variance keeps growing."""
    checkpoint = target_checkpoint(tmp_path, {"relative": True}, stride=stride)
    transform = LatchedForecastTransform.from_checkpoint(checkpoint)
    assert transform.relative
    transform.observe_reset(recorded_steps[0].clone())
    ages = [1, 3, 40]  # with stride 2, shifts 0, 1 and past the horizon
    latched = synthetic_latch(transform, ages)
    loc, scale = transform.advanced()
    zero = torch.zeros(1, TARGET_DIM)
    for env, age in enumerate(ages):
        path = torch.cat([zero, latched[env]])  # L[0] = 0: the displacement at the latch step
        shift = min(age // stride, HORIZON)
        expected = torch.stack([path[min(shift + k, HORIZON)] - path[shift] for k in range(1, HORIZON + 1)])
        torch.testing.assert_close(loc[env], expected, msg=lambda m, e=env: f"env {e}: {m}")
        expected_scale = scale_by_hand(latched[env].sqrt() + 1, age, stride)
        torch.testing.assert_close(scale[env], expected_scale, msg=lambda m, e=env: f"env {e}: {m}")
    assert bool((scale[2, -1] > scale[2, 0]).all()), (
        "an outage past the horizon: the held step grows less sure"
    )


def test_a_target_relative_to_the_gripper_follows_the_gripper(recorded_steps, tmp_path):
    """For the object minus the gripper, the latched offset moves by the gripper's own motion since
    the latch (read from proprioception, dims 0-1 as in the data config)."""
    checkpoint = target_checkpoint(tmp_path, {"relative_to": GRIPPER})
    transform = LatchedForecastTransform.from_checkpoint(checkpoint, rule="latched")
    assert transform.reference_key == keys.obs_key("proprio")
    steps = camera_outages(recorded_steps, {0: range(6, 40)})
    gripper = [s.get(keys.obs_key("proprio"))[0, :2].clone() for s in steps]
    for t in (9, 10):  # proprioception lost (zeroed, as ModalityDropout does): its last reading stands
        steps[t][keys.obs_key("proprio")].zero_()
        steps[t][keys.present_key("proprio")].fill_(False)
        gripper[t] = gripper[8]
    plain = replay(ForecastTransform.from_checkpoint(checkpoint), steps)
    served = replay(transform, steps)
    latch_step = 5  # the last step with the camera through the window
    for t in range(latch_step, 12):
        expected = advanced_by_hand(plain[latch_step][keys.FORECAST_LOC][0], t - latch_step)
        expected = expected + gripper[latch_step] - gripper[t]
        torch.testing.assert_close(
            served[t][keys.FORECAST_LOC][0], expected, msg=lambda m, t=t: f"step {t}: {m}"
        )
    assert any(not torch.equal(gripper[latch_step], g) for g in gripper[6:12]), "the gripper moved"


def test_rules_fresh_scale_and_precision(recorded_steps, absolute_checkpoint):
    steps = camera_outages(recorded_steps, {0: range(6, 40), 1: range(6, 40), 2: range(6, 40)})
    fresh = replay(ForecastTransform.from_checkpoint(absolute_checkpoint), steps)
    by_rule = {
        rule: replay(LatchedForecastTransform.from_checkpoint(absolute_checkpoint, rule=rule), steps)
        for rule in ("latched", "fresh", "scale", "precision")
    }
    t = 12
    held_loc, held_scale = (
        by_rule["latched"][t][keys.FORECAST_LOC],
        by_rule["latched"][t][keys.FORECAST_SCALE],
    )
    loc, scale = fresh[t][keys.FORECAST_LOC], fresh[t][keys.FORECAST_SCALE]
    torch.testing.assert_close(by_rule["fresh"][t][keys.FORECAST_LOC], loc)
    assert by_rule["fresh"][t][keys.FORECAST_AGE].eq(0).all()
    latch_smaller = held_scale.mean((1, 2)) < scale.mean((1, 2))
    chosen = torch.where(latch_smaller[:, None, None], held_loc, loc)
    torch.testing.assert_close(by_rule["scale"][t][keys.FORECAST_LOC], chosen)
    weights = held_scale.pow(-2), scale.pow(-2)
    combined = (held_loc * weights[0] + loc * weights[1]) / (weights[0] + weights[1])
    torch.testing.assert_close(by_rule["precision"][t][keys.FORECAST_LOC], combined)
    torch.testing.assert_close(
        by_rule["precision"][t][keys.FORECAST_SCALE], (weights[0] + weights[1]).rsqrt()
    )
    assert by_rule["precision"][t][keys.FORECAST_AGE].tolist() == [float(t - 5)] * RECORDED_ENVS


def test_the_latch_round_trips_through_the_state_dict(recorded_steps, absolute_checkpoint):
    steps = camera_outages(recorded_steps, {0: range(5, 30), 1: range(9, 30), 2: range(2, 4)})
    running = LatchedForecastTransform.from_checkpoint(absolute_checkpoint)
    restored = LatchedForecastTransform.from_checkpoint(absolute_checkpoint)
    replay(running, steps[:12])
    restored.load_state_dict(running.state_dict())
    for step in steps[12:20]:
        expected, got = running.observe_step(step.clone()), restored.observe_step(step.clone())
        for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.FORECAST_AGE, keys.FORECAST_VALID):
            torch.testing.assert_close(got[key], expected[key])
    assert restored.state_dict()["_age"].tolist() == running.state_dict()["_age"].tolist()
    assert running.state_dict()["_age"][:2].min() > 0, "envs 0 and 1 are mid-outage"


def test_spec_declares_the_age_and_the_forecast(absolute_checkpoint):
    env = TransformedEnv(stamp_envs(2), LatchedForecastTransform.from_checkpoint(absolute_checkpoint))
    try:
        check_env_specs(env, seed=0)
        spec = env.observation_spec
        assert spec[keys.FORECAST_AGE].shape == (2,) and spec[keys.FORECAST_AGE].dtype == torch.float32
        assert spec[keys.FORECAST_LOC].shape == (2, HORIZON, TARGET_DIM)
    finally:
        env.close()


@pytest.mark.parametrize(
    "options, message",
    [
        ({"rule": "newest"}, "unknown rule 'newest'"),
        ({"latch_on": ["lidar"]}, "latch_on must name some of the model's modalities"),
        ({"latch_on": []}, "latch_on must name some of the model's modalities"),
    ],
)
def test_bad_options_are_named(absolute_checkpoint, options, message):
    with pytest.raises(ValueError, match=message):
        LatchedForecastTransform.from_checkpoint(absolute_checkpoint, **options)


def test_a_reference_no_modality_reads_is_refused(tmp_path):
    checkpoint = target_checkpoint(tmp_path, {"relative_to": {"feature": "observation.goal", "dims": [0, 1]}})
    with pytest.raises(ValueError, match="no model modality reads"):
        LatchedForecastTransform.from_checkpoint(checkpoint)


def test_the_normalised_frame_serves_the_same_forecast(recorded_steps, tmp_path):
    """``denormalize=False`` (what a BC policy reads): the latch is re-based in the target's units."""
    checkpoint = target_checkpoint(tmp_path, {"relative": True})
    steps = camera_outages(recorded_steps, {0: range(4, 40), 1: range(9, 40), 2: range(2, 6)})
    units = replay(LatchedForecastTransform.from_checkpoint(checkpoint, rule="latched"), steps)
    normalised_transform = LatchedForecastTransform.from_checkpoint(
        checkpoint, rule="latched", denormalize=False
    )
    normalised = replay(normalised_transform, steps)
    normalizer = normalised_transform.normalizer
    for t in (3, 8, 15, 30):
        torch.testing.assert_close(
            normalizer.denormalize_target(normalised[t][keys.FORECAST_LOC]), units[t][keys.FORECAST_LOC]
        )
        torch.testing.assert_close(
            normalizer.denormalize_target_scale(normalised[t][keys.FORECAST_SCALE]),
            units[t][keys.FORECAST_SCALE],
        )


def test_the_latch_follows_the_transform_to_a_device(recorded_steps, tmp_path):
    transform = LatchedForecastTransform.from_checkpoint(
        target_checkpoint(tmp_path, {"relative_to": GRIPPER})
    )
    replay(transform, camera_outages(recorded_steps, {0: range(2, 8), 1: range(3, 8), 2: range(4, 8)})[:8])
    latch = {"_latched_loc", "_latched_scale", "_latched_reference", "_last_reference", "_age", "_has_latch"}
    assert latch <= set(transform.state_dict()), "the latch is state"
    transform.to("meta")
    assert {t.device.type for t in transform.buffers()} == {"meta"}
    assert transform._age.shape == (RECORDED_ENVS,), "moved, not reallocated"  # noqa: SLF001
