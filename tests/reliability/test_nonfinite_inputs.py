"""NaN/Inf under a present modality at run time: one rule everywhere.

The model API (forecaster and every baseline) refuses such a batch naming the key and the
samples, or with ``nonfinite="absent"`` reads those samples' modality as absent. The RL glue
(`HistoryWindow`, `ForecastTransform`, the world model) always reads a non-finite sensor as
absent, so a rollout never yields a NaN forecast or action.
"""

import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.modules.planners import CEMPlanner

from mmf_rl import keys
from mmf_rl.models import build_model
from mmf_rl.rl import ForecasterWorldModelEnv, PushObjective
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, TARGET_DIM, make_batch
from tests.envs.stamp_env import StampEnv
from tests.rl.test_transforms import PUSH_SPECS, write_checkpoint

SMALL_SIZES = {"d_model": 16, "head_hidden": 32}
MODEL_CONFIGS = {
    "forecaster": {**SMALL_SIZES, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32},
    "lf_lstm": SMALL_SIZES,
    "mvae": {**SMALL_SIZES, "d_latent": 4},
    "mult": {**SMALL_SIZES, "num_heads": 2, "mlp_hidden": 32},
}
BAD_ROWS = [1, 3]


def small_model(name: str, **options):
    torch.manual_seed(0)
    model = build_model(
        {"name": name, **MODEL_CONFIGS[name], **options}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM
    )
    return model.eval()


def poisoned_batch(value: float):
    batch = make_batch(6)
    batch.get(keys.obs_key("force"))[BAD_ROWS, 2, 1] = value
    return batch


@pytest.mark.parametrize("name", sorted(MODEL_CONFIGS))
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_the_model_api_refuses_nonfinite_present_values_naming_key_and_samples(name, value):
    model = small_model(name)
    for call in (model, lambda td: model.sample(td, 2)):
        with pytest.raises(
            ValueError,
            match=r"td\[\('obs', 'force'\)\] holds NaN or Inf in 2 sample\(s\) where "
            r"\('present', 'force'\) is True \(batch indices \[1, 3\]\).*"
            r"nonfinite='absent'",
        ):
            call(poisoned_batch(value))


@pytest.mark.parametrize("name", sorted(MODEL_CONFIGS))
def test_nonfinite_absent_reads_those_samples_as_absent(name):
    model = small_model(name, nonfinite="absent")
    batch = poisoned_batch(float("nan"))
    with torch.no_grad():
        out = model(batch.clone())
        absent = make_batch(6)
        absent.get(keys.present_key("force"))[BAD_ROWS] = False
        expected = model(absent)
    assert torch.isfinite(out.get(keys.FORECAST_LOC)).all()
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), expected.get(keys.FORECAST_LOC))
    assert out.get(keys.present_key("force")).tolist() == [i not in BAD_ROWS for i in range(6)], (
        "the batch says which samples were read as absent"
    )
    # The untouched modalities and a clean batch are unaffected.
    assert out.get(keys.present_key("image")).all() and out.get(keys.present_key("proprio")).all()


def test_nonfinite_absent_with_nothing_left_says_why():
    model = small_model("forecaster", nonfinite="absent")
    batch = make_batch(4, present={"image": torch.tensor([True, True, False, True])})
    for name in ("force", "proprio"):
        batch.get(keys.obs_key(name))[2] = float("nan")
    with pytest.raises(
        ValueError,
        match=r"1 sample\(s\) have no present modality \(after NaN/Inf made "
        r"\['force', 'proprio'\] absent\) \(batch indices \[2\]\)",
    ):
        model(batch)


def test_an_unknown_nonfinite_option_is_refused():
    with pytest.raises(ValueError, match="ForecasterConfig.nonfinite must be one of \\('raise', 'absent'\\)"):
        small_model("forecaster", nonfinite="zero")
    with pytest.raises(ValueError, match="MVAEConfig.nonfinite must be one of"):
        small_model("mvae", nonfinite="ignore")


def test_a_nonfinite_future_action_is_refused_by_a_world_model():
    model = build_model(
        {"name": "forecaster", **MODEL_CONFIGS["forecaster"]},
        SMALL_MODALITIES,
        HISTORY,
        HORIZON,
        TARGET_DIM,
        action_shape=(HORIZON, 3),
    ).eval()
    batch = make_batch(3)
    batch.set(keys.FUTURE_ACTION, torch.zeros(3, HORIZON, 3))
    batch.get(keys.FUTURE_ACTION)[2, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"td\['future_action'\] holds NaN or Inf \(batch indices \[2\]\)"):
        model(batch)


# -- RL glue -----------------------------------------------------------------------------------

NAN_STEPS = {2: float("nan"), 3: float("inf")}  # force readings the sensor garbles


class GarbledForceEnv(StampEnv):
    """`StampEnv` whose force reads NaN/Inf at `NAN_STEPS` (``flag_absent``: reports it absent instead)."""

    def __init__(self, flag_absent: bool = False):
        super().__init__()
        self.flag_absent = flag_absent

    def _observation(self):
        td = super()._observation()
        if self.t in NAN_STEPS:
            if self.flag_absent:
                td.set(keys.present_key("force"), torch.tensor(False))
            else:
                td.get(keys.obs_key("force"))[0] = NAN_STEPS[self.t]
        return td


def test_forecast_transform_reads_a_nonfinite_sensor_as_absent(checkpoint_dir):
    rollouts = {}
    for flag_absent in (False, True):
        env = TransformedEnv(GarbledForceEnv(flag_absent), ForecastTransform.from_checkpoint(checkpoint_dir))
        rollouts[flag_absent] = env.rollout(7, break_when_any_done=False)
    garbled, flagged = rollouts[False], rollouts[True]
    loc = garbled.get(("next", *keys.FORECAST_LOC))
    assert torch.isfinite(loc).all() and garbled.get(("next", *keys.FORECAST_VALID)).all()
    torch.testing.assert_close(loc, flagged.get(("next", *keys.FORECAST_LOC)))


def test_history_window_never_holds_a_nonfinite_value(checkpoint_dir):
    forecast = ForecastTransform.from_checkpoint(checkpoint_dir)
    env = TransformedEnv(
        GarbledForceEnv(), HistoryWindow.for_model(forecast.model, forecast.normalizer.stats)
    )
    td = env.rollout(7, break_when_any_done=False)
    force = td.get(("next", keys.HISTORY, *keys.obs_key("force")))
    assert torch.isfinite(force).all()
    present = td.get(("next", keys.HISTORY, *keys.present_key("force"))).tolist()
    # Step t's window holds steps t-2..t (H = 3): absent while it holds step 2 or 3.
    assert present == [t + 1 not in range(2, 2 + 2 + 2) for t in range(7)]
    forecast.model.validate(td.get(("next", keys.HISTORY)))  # a valid batch: no NaN under a present modality


@pytest.fixture(scope="module")
def checkpoint_dir(tmp_path_factory):
    return write_checkpoint(tmp_path_factory.mktemp("ckpt"), PUSH_SPECS)


def test_world_model_and_planner_read_a_nonfinite_history_as_absent(push_world_model, push_history_env):
    real = push_history_env.rollout(3, break_when_any_done=False)[-1].get("next")
    window = real.get(keys.HISTORY).unsqueeze(0)
    garbled, flagged = window.clone(), window.clone()
    garbled.get(keys.obs_key("force"))[0, -1, 0] = float("nan")
    flagged.set(keys.present_key("force"), torch.tensor([False]))
    actions = torch.zeros(1, 2, push_world_model.action_steps, push_world_model.action_dim)
    forecast = push_world_model.forecast(*push_world_model.encode(garbled), actions)
    assert torch.isfinite(forecast).all()
    torch.testing.assert_close(
        forecast, push_world_model.forecast(*push_world_model.encode(flagged), actions)
    )

    objective = PushObjective()
    env = ForecasterWorldModelEnv(
        push_world_model, objective, push_history_env.action_spec, push_history_env.observation_spec
    )
    state = real.select(*objective.in_keys).set(keys.HISTORY, garbled[0])
    planner = CEMPlanner(
        env, planning_horizon=push_world_model.action_steps, optim_steps=2, num_candidates=8, top_k=2
    )
    action = planner.planning(env.reset(state))
    assert torch.isfinite(action).all()
