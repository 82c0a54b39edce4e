from __future__ import annotations

import logging
import pickle

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.envs import Compose, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mmf_rl import keys
from mmf_rl.checkpoint import save_checkpoint
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.envs.modality_dropout import ModalityDropout, UniformBursts
from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv
from mmf_rl.keys import FORECAST_VALID, ModalitySpec
from mmf_rl.models import build_model, saved_config
from mmf_rl.models.loading import load_trained_model
from mmf_rl.rl.latched_forecast import LatchedForecastTransform
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow
from tests.envs.conftest import IMAGE_SIZE
from tests.envs.stamp_env import MODALITIES, VECTOR_DIMS, stamp_envs
from tests.rl.conftest import RECORDED_ENVS

HISTORY, HORIZON, TARGET_DIM = 3, 4, 2
MODEL_IMAGE = 16  # smaller than the env's frames: the transform resizes them


def make_stats(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    stats = {}
    for name, dim in [*VECTOR_DIMS.items(), ("target", TARGET_DIM)]:
        stats[f"{name}/mean"] = torch.randn(dim, generator=g)
        stats[f"{name}/std"] = torch.rand(dim, generator=g) + 0.5
    return stats


def write_checkpoint(
    directory,
    specs,
    stride: int = 1,
    prior: str = "standard",
    seed: int = 0,
    partial_windows: bool | None = None,
    decoder_input: str = "mixed",
):
    """A checkpoint of an untrained forecaster; ``partial_windows`` (``None``: no key, an older run)
    is its run's ``data.partial_windows``."""
    torch.manual_seed(seed)
    model = build_model(
        {
            "name": "forecaster",
            "d_model": 16,
            "d_latent": 4,
            "num_heads": 2,
            "mlp_hidden": 32,
            "head_hidden": 32,
            "prior": prior,
            "decoder_input": decoder_input,
        },
        specs,
        HISTORY,
        HORIZON,
        TARGET_DIM,
    )
    data_config = {"history": HISTORY, "horizon": HORIZON, "stride": stride}
    if partial_windows is not None:
        data_config["partial_windows"] = partial_windows
    save_checkpoint(
        directory,
        1,
        model.state_dict(),
        tensors=make_stats(),
        meta={
            "model_config": saved_config("forecaster", model),
            "config": {"data": data_config},
        },
    )
    return directory


PUSH_SPECS = [
    ModalitySpec("image", "image", (3, MODEL_IMAGE, MODEL_IMAGE), encoder_kwargs={"channels": (8, 16)}),
    ModalitySpec("force", "sequence", (6,)),
    ModalitySpec("proprio", "sequence", (17,)),
]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_checkpoint(tmp_path_factory.mktemp("ckpt"), PUSH_SPECS)


@pytest.fixture(scope="module")
def push_envs():
    """Two real push envs (a GL context each, about a second to make), for the tests below that wrap
    them in a `TransformedEnv` of their own (which leaves its base env open) and seed them."""
    env = SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE))
    yield env
    env.close()


def test_forecast_env_passes_check_env_specs(checkpoint, push_envs):
    env = TransformedEnv(
        push_envs,
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.3, seed=0),
            ForecastTransform.from_checkpoint(checkpoint, num_samples=3),
        ),
    )
    check_env_specs(env, seed=0)
    spec = env.observation_spec
    assert spec[keys.FORECAST_LOC].shape == (2, HORIZON, TARGET_DIM)
    assert spec[keys.FORECAST_SAMPLES].shape == (2, 3, HORIZON, TARGET_DIM)


def hand_built_window(frames: list, normalizer: Normalizer, t: int) -> TensorDict:
    """The window ending at frame ``t`` (frames before the reset repeat frame 0), built like the data."""
    steps = [max(0, t - HISTORY + 1 + i) for i in range(HISTORY)]
    batch = frames[0].batch_size
    window = TensorDict(batch_size=batch)
    for spec in PUSH_SPECS:
        values = torch.stack([frames[s].get(spec.obs_key) for s in steps], dim=1)
        present = torch.stack([frames[s].get(spec.present_key) for s in steps], dim=1).all(1)
        if spec.kind == "image":
            size = spec.shape[-2:]
            flat = F.interpolate(
                values.flatten(0, 1).float() / 255,
                size=size,
                mode="bilinear",
                antialias=True,
                align_corners=False,
            )
            values = (flat * 255).round().clamp(0, 255).to(torch.uint8).view(*values.shape[:3], *size)
        else:
            values = normalizer.normalize(spec.name, values) * present[:, None, None]
        window.set(spec.obs_key, values)
        window.set(spec.present_key, present)
    return window


def test_forecast_equals_the_model_on_the_window_built_by_hand(checkpoint, push_envs):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    model, normalizer = forecast.model, forecast.normalizer
    env = TransformedEnv(
        push_envs,
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2),
            forecast,
        ),
    )
    env.set_seed(0)
    td = env.rollout(6, break_when_any_done=False)
    frames = [td[:, 0].exclude("next")] + [td["next"][:, t] for t in range(td.shape[1])]
    saw_absent = False
    for t in range(1, len(frames)):
        window = hand_built_window(frames, normalizer, t)
        saw_absent |= not all(window.get(s.present_key).all() for s in PUSH_SPECS)
        with torch.no_grad():
            out = model(window)
        torch.testing.assert_close(
            td["next", keys.FORECAST, "loc"][:, t - 1], normalizer.denormalize_target(out[keys.FORECAST_LOC])
        )
        torch.testing.assert_close(
            td["next", keys.FORECAST, "scale"][:, t - 1],
            normalizer.denormalize_target_scale(out[keys.FORECAST_SCALE]),
        )
    assert saw_absent, "the rollout should exercise windows with a missing modality"
    assert td["next", FORECAST_VALID].all()


# -- the lean (traced) path, on the project's recorded pushes -------------------------------------


def with_outages(steps: list[TensorDict], num_envs: int, nan_as_absent: bool = False) -> list[TensorDict]:
    """The first ``num_envs`` envs of ``steps`` with sensor faults, env ``e`` shifted by ``5 e`` steps:
    the camera dies at step 6 for good; force reads NaN at steps 10-11 (or, ``nan_as_absent``,
    is flagged absent there, over garbage); every sensor is absent at steps 20-21."""
    out = []
    for t, step in enumerate(steps):
        step = step[:num_envs].clone()
        for env in range(num_envs):
            local = t - 5 * env
            if local >= 6:
                step[keys.present_key("image")][env] = False
            if local in (10, 11):
                if nan_as_absent:
                    step[keys.obs_key("force")][env] = 1e6
                    step[keys.present_key("force")][env] = False
                else:
                    step[keys.obs_key("force")][env, 2] = float("nan")
            if local in (20, 21):
                for name in MODALITIES:
                    step[keys.present_key(name)][env] = False
        out.append(step)
    return out


def replay(forecast: ForecastTransform, steps: list[TensorDict]) -> list[TensorDict]:
    """The transform's outputs for a reset on ``steps[0]`` then a step on each of the others (the
    transform alone, fed what an env would emit)."""
    outputs = [forecast.observe_reset(steps[0].clone())]
    outputs += [forecast.observe_step(step.clone()) for step in steps[1:]]
    return outputs


def graphs(forecast: ForecastTransform) -> int:
    traced = forecast._traced
    return len(traced.encoders) + (traced.everywhere is not None) + (traced.head is not None)


def assert_same_forecasts(lean: list[TensorDict], eager: list[TensorDict]) -> None:
    for t, (a, b) in enumerate(zip(lean, eager, strict=True)):
        for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
            torch.testing.assert_close(a[key], b[key], msg=lambda m, t=t, key=key: f"step {t}, {key}: {m}")
        assert torch.equal(a[FORECAST_VALID], b[FORECAST_VALID]), f"step {t}"


@pytest.mark.parametrize("prior", ["standard", "learned"])
@pytest.mark.parametrize("num_envs", [1, RECORDED_ENVS])
def test_lean_forecast_equals_the_eager_forward_on_recorded_pushes(recorded_steps, tmp_path, num_envs, prior):
    """The default (traced) path writes the eager TensorDict forward's forecasts through a camera
    that dies, NaN force readings and windows with no sensor; with 3 envs these hit some envs only."""
    checkpoint = write_checkpoint(tmp_path, PUSH_SPECS, prior=prior)
    steps = with_outages(recorded_steps, num_envs)
    lean_transform = ForecastTransform.from_checkpoint(checkpoint)
    lean = replay(lean_transform, steps)
    eager = replay(ForecastTransform.from_checkpoint(checkpoint, trace=False), steps)
    assert_same_forecasts(lean, eager)

    valid = torch.stack([out[FORECAST_VALID] for out in lean])
    assert valid[0].all() and not valid.all(), "the replay should hold windows without any sensor"
    assert all(torch.isfinite(out[keys.FORECAST_LOC]).all() for out in lean), "a NaN reading is absent"
    traced = lean_transform._traced
    assert traced.everywhere is not None and traced.head is not None, "both traced paths should run"
    assert not lean[-1][keys.FORECAST_LOC].is_inference(), "a policy can train on the forecasts"


def test_lean_forecast_reads_a_nan_reading_as_an_absent_sensor(recorded_steps, checkpoint):
    with_nan = replay(ForecastTransform.from_checkpoint(checkpoint), with_outages(recorded_steps, 1))
    flagged = replay(
        ForecastTransform.from_checkpoint(checkpoint), with_outages(recorded_steps, 1, nan_as_absent=True)
    )
    assert_same_forecasts(with_nan, flagged)


def test_lean_forecast_follows_a_new_batch_size_and_refuses_an_unannounced_one(recorded_steps, checkpoint):
    steps = with_outages(recorded_steps, RECORDED_ENVS)
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    replay(forecast, [step[:1] for step in steps[:8]])
    lean = replay(forecast, steps)  # a reset of a batch of 3: new history, graphs traced again
    assert_same_forecasts(lean, replay(ForecastTransform.from_checkpoint(checkpoint, trace=False), steps))
    with pytest.raises(RuntimeError, match=r"env batch is \[2\] but was \[3\] at the last reset"):
        forecast.observe_step(steps[1][:2].clone())


def test_a_running_lean_forecast_transform_pickles(recorded_steps, checkpoint):
    """A transform sent to a worker mid-rollout: its graphs stay behind, the copy traces its own."""
    steps = with_outages(recorded_steps, 1)
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    replay(forecast, steps[:8])
    copied = pickle.loads(pickle.dumps(forecast))
    for step in steps[8:12]:
        assert_same_forecasts([copied.observe_step(step.clone())], [forecast.observe_step(step.clone())])


def test_lean_forecast_follows_in_place_weight_updates(recorded_steps, tmp_path, checkpoint):
    steps = with_outages(recorded_steps, 1)
    other = write_checkpoint(tmp_path, PUSH_SPECS, seed=1)
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    before = replay(forecast, steps[:5])
    eager_other = ForecastTransform.from_checkpoint(other, trace=False)
    expected = replay(eager_other, steps)
    assert not torch.allclose(before[-1][keys.FORECAST_LOC], expected[4][keys.FORECAST_LOC])
    forecast.model.load_state_dict(eager_other.model.state_dict())
    after = [forecast.observe_step(step.clone()) for step in steps[5:]]
    assert_same_forecasts(after, expected[5:])


def test_lean_forecast_applies_and_follows_the_scale_factors(recorded_steps, checkpoint):
    """Factors fitted while graphs are in use (an in-place change of a buffer, frozen into the
    graphs) are applied from the next step on, per env's presence pattern, as the eager forward does."""
    steps = with_outages(recorded_steps, RECORDED_ENVS)
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    eager = ForecastTransform.from_checkpoint(checkpoint, trace=False)
    before = replay(forecast, steps[:5])
    factors = torch.linspace(0.5, 4.0, 2 ** len(PUSH_SPECS))
    for transform in (forecast, eager):
        transform.model.scale_calibration.factors.copy_(factors)
    expected = replay(eager, steps)
    assert_same_forecasts([forecast.observe_step(step.clone()) for step in steps[5:]], expected[5:])
    assert not torch.allclose(before[-1][keys.FORECAST_SCALE], expected[4][keys.FORECAST_SCALE])


def test_lean_forecast_keeps_a_bounded_set_of_graphs_whatever_the_outages(recorded_steps, checkpoint):
    """At most one graph per modality encoder, one for the rest and one for full presence, for any
    mix of presence across envs and steps (a graph per presence pattern and row count made the
    memory of 16 envs grow for thousands of steps)."""
    generator = torch.Generator().manual_seed(0)
    steps = []
    for step in recorded_steps * 3:
        step = step.clone()
        for name in MODALITIES:
            step[keys.present_key(name)] &= torch.rand(RECORDED_ENVS, generator=generator) > 0.3
        steps.append(step)
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    lean = replay(forecast, steps)
    assert graphs(forecast) <= len(PUSH_SPECS) + 2
    assert_same_forecasts(lean, replay(ForecastTransform.from_checkpoint(checkpoint, trace=False), steps))


# -- the history is module state ------------------------------------------------------------------


def synthetic_steps(num_envs: int = RECORDED_ENVS, length: int = 32, seed: int = 0) -> list[TensorDict]:
    """Seeded random observations of ``num_envs`` envs, every sensor flagged present."""
    generator = torch.Generator().manual_seed(seed)
    steps = []
    for _ in range(length):
        image = torch.randint(0, 256, (num_envs, 3, IMAGE_SIZE, IMAGE_SIZE), generator=generator)
        step = {keys.obs_key("image"): image.to(torch.uint8)}
        for name, dim in VECTOR_DIMS.items():
            step[keys.obs_key(name)] = torch.randn(num_envs, dim, generator=generator)
        for name in MODALITIES:
            step[keys.present_key(name)] = torch.ones(num_envs, dtype=torch.bool)
        steps.append(TensorDict(step, batch_size=[num_envs]))
    return steps


# Sums over horizon and target dims of the forecasts per env at steps 0, 11, 21 and 31 of
# `synthetic_steps` with `with_outages`, written by the transform whose history was a host-side
# dict of tensors (before it became buffers): the forecasts must not change. Its forecaster read
# the raw tokens (what `build_model` built then without `decoder_input`).
HOST_HISTORY_FORECASTS = {
    0: ([-8.4109, -8.2584, -8.3146], [7.6015, 7.4677, 7.5475]),
    11: ([-8.6139, -8.3611, -8.2798], [7.73, 7.5582, 7.6711]),
    21: ([-7.8392, -8.6183, -8.4913], [10.4431, 7.5034, 7.8245]),
    31: ([-8.4768, -8.4823, -7.8392], [7.4101, 7.5015, 10.4431]),
}


@pytest.mark.parametrize("trace", [True, False])
def test_forecasts_are_unchanged_by_keeping_the_history_in_buffers(tmp_path, trace):
    checkpoint = write_checkpoint(tmp_path, PUSH_SPECS, decoder_input="tokens")
    outputs = replay(
        ForecastTransform.from_checkpoint(checkpoint, trace=trace),
        with_outages(synthetic_steps(), RECORDED_ENVS),
    )
    for t, (loc, scale) in HOST_HISTORY_FORECASTS.items():
        torch.testing.assert_close(
            outputs[t][keys.FORECAST_LOC].sum((1, 2)), torch.tensor(loc), rtol=0, atol=2e-4
        )
        torch.testing.assert_close(
            outputs[t][keys.FORECAST_SCALE].sum((1, 2)), torch.tensor(scale), rtol=0, atol=2e-4
        )


def test_history_and_statistics_follow_the_transform_to_a_device(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    replay(forecast, synthetic_steps(length=4))
    history = {name for name, _ in forecast.named_buffers() if name.startswith(("_frames_", "_present_"))}
    assert len(history) == 2 * len(PUSH_SPECS), "one frame and one presence buffer per modality"
    forecast.to("meta")
    assert {t.device.type for t in forecast.buffers()} == {"meta"}
    assert {t.device.type for t in forecast.normalizer.stats.values()} == {"meta"}
    assert next(forecast.model.parameters()).device.type == "meta"


@pytest.mark.parametrize("transform", ["forecast", "history"])
def test_history_round_trips_through_the_state_dict(checkpoint, transform):
    """A fresh transform loaded with a running one's state dict continues its history: same
    windows and forecasts from the next step on, without a reset of its own."""

    def build():
        forecast = ForecastTransform.from_checkpoint(checkpoint)
        if transform == "forecast":
            return forecast
        return HistoryWindow.for_model(forecast.model, forecast.normalizer.stats)

    steps = with_outages(synthetic_steps(), RECORDED_ENVS)
    running, restored = build(), build()
    replay(running, steps[:9])
    restored.load_state_dict(running.state_dict())
    for step in steps[9:14]:
        expected, got = running.observe_step(step.clone()), restored.observe_step(step.clone())
        for key in expected.keys(True, True):  # the observations hold NaN readings
            torch.testing.assert_close(
                got[key], expected[key], equal_nan=True, msg=lambda m, k=key: f"{k}: {m}"
            )
    assert (restored.window() == running.window()).all()


def test_forecast_history_resets_with_the_envs_that_reset(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    env = TransformedEnv(stamp_envs(3), forecast)
    stats = forecast.normalizer.stats

    def window_stamps(name: str = "force") -> list[list[int]]:
        values = forecast.window().get(keys.obs_key(name))[..., 0]  # normalised stamps [envs, H]
        raw = values * stats[f"{name}/std"][0] + stats[f"{name}/mean"][0]
        return raw.round().long().tolist()

    try:
        td = env.reset()
        assert window_stamps() == [[1] * 3, [1001] * 3, [2001] * 3], "a reset fills the history with frame 0"
        for _ in range(4):
            td = env.step(env.rand_action(td))["next"]
        assert window_stamps() == [[3, 4, 5], [1003, 1004, 1005], [2003, 2004, 2005]]
        td["_reset"] = torch.tensor([[False], [True], [False]])
        td = env.reset(td)
        assert window_stamps() == [[3, 4, 5], [1101] * 3, [2003, 2004, 2005]], "only env 1 restarts"
        td = env.step(env.rand_action(td))["next"]
        assert window_stamps() == [[4, 5, 6], [1101, 1101, 1102], [2004, 2005, 2006]]
        image = forecast.window().get(keys.obs_key("image"))
        assert image.shape == (3, HISTORY, 3, MODEL_IMAGE, MODEL_IMAGE)
        assert image[1, :, 0, 0, 0].tolist() == [1101 % 256, 1101 % 256, 1102 % 256]
    finally:
        env.close()


def test_forecast_window_uses_the_checkpoint_stride(tmp_path):
    forecast = ForecastTransform.from_checkpoint(write_checkpoint(tmp_path, PUSH_SPECS, stride=2))
    env = TransformedEnv(stamp_envs(1), forecast)
    try:
        td = env.reset()
        for _ in range(6):
            td = env.step(env.rand_action(td))["next"]
        image = forecast.window().get(keys.obs_key("image"))
        assert image[0, :, 0, 0, 0].tolist() == [3, 5, 7]
    finally:
        env.close()


def test_forecast_without_any_present_modality_is_the_target_marginal(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint, num_samples=2)
    env = TransformedEnv(
        stamp_envs(2),
        Compose(
            ModalityDropout(
                list(MODALITIES), outage_prob={"image": 1.0, "force": 1.0, "proprio": 0.0}, outage="episode"
            ),
            forecast,
        ),
    )
    try:
        td = env.reset()
        td = env.step(env.rand_action(td))["next"]
        assert td[FORECAST_VALID].all(), "proprio alone is enough"
        env.transform[0].outage_prob.fill_(1.0)
        td = env.reset()
    finally:
        env.close()
    stats = forecast.normalizer.stats
    assert not td[FORECAST_VALID].any()
    assert torch.equal(td[keys.FORECAST_LOC], stats["target/mean"].expand(2, HORIZON, -1))
    assert torch.equal(td[keys.FORECAST_SCALE], stats["target/std"].expand(2, HORIZON, -1))
    assert torch.isfinite(td[keys.FORECAST_SAMPLES]).all()


@pytest.mark.parametrize(
    "specs,problem",
    [
        (
            [ModalitySpec("wrist", "image", (3, 16, 16), encoder_kwargs={"channels": (8, 16)})],
            "'wrist' is not emitted",
        ),
        ([ModalitySpec("proprio", "sequence", (20,))], "'proprio' is float32 [17], expected float [20]"),
        (
            [ModalitySpec("image", "image", (1, 16, 16), encoder_kwargs={"channels": (8, 16)})],
            "expected uint8 [1, h, w]",
        ),
    ],
)
def test_checkpoint_that_does_not_match_the_env_is_refused(tmp_path, specs, problem):
    env = TransformedEnv(stamp_envs(2), ForecastTransform.from_checkpoint(write_checkpoint(tmp_path, specs)))
    try:
        with pytest.raises(ValueError) as error:
            env.observation_spec  # noqa: B018 - computing the spec runs the check
    finally:
        env.close(raise_if_closed=False)  # the batched env never started its workers
    message = str(error.value)
    assert problem in message
    assert "Checkpoint modalities: [" in message and specs[0].name in message
    for name in MODALITIES:
        assert f"{name} (" in message, "the env's side is listed"


def test_stats_without_a_modality_are_refused(checkpoint):
    transform = ForecastTransform.from_checkpoint(checkpoint)
    stats = {k: v for k, v in make_stats().items() if not k.startswith("force/")}
    with pytest.raises(KeyError, match="force/mean"):
        ForecastTransform(transform.model, stats)


# -- HistoryWindow -------------------------------------------------------------------------------


def test_history_window_is_the_model_batch_built_by_hand(checkpoint, push_envs):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    history = HistoryWindow.for_model(forecast.model, forecast.normalizer.stats)
    env = TransformedEnv(
        push_envs,
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2), history
        ),
    )
    check_env_specs(env, seed=0)
    assert env.observation_spec[keys.HISTORY, keys.OBS, "image"].shape == (
        2,
        HISTORY,
        3,
        MODEL_IMAGE,
        MODEL_IMAGE,
    )
    env.set_seed(0)
    td = env.rollout(6, break_when_any_done=False)
    frames = [td[:, 0].exclude("next")] + [td["next"][:, t] for t in range(td.shape[1])]
    for t in range(1, len(frames)):
        expected = hand_built_window(frames, forecast.normalizer, t)
        written = td["next", keys.HISTORY][:, t - 1]
        for spec in PUSH_SPECS:
            torch.testing.assert_close(written.get(spec.obs_key), expected.get(spec.obs_key))
            assert torch.equal(written.get(spec.present_key), expected.get(spec.present_key))
    forecast.model.validate(td["next", keys.HISTORY][:, -1])  # a batch of the key contract


def test_forecast_transform_refuses_a_world_model_and_names_the_way_to_plan(tmp_path):
    torch.manual_seed(0)
    model = build_model(
        {
            "name": "forecaster",
            "d_model": 16,
            "d_latent": 4,
            "num_heads": 2,
            "mlp_hidden": 32,
            "head_hidden": 32,
        },
        PUSH_SPECS,
        HISTORY,
        HORIZON,
        TARGET_DIM,
        action_shape=(HORIZON, 4),
    )
    with pytest.raises(ValueError, match="action-conditioned world model.*HistoryWindow.*SequenceCEMPlanner"):
        ForecastTransform(model, make_stats())


def test_per_step_presence_keeps_a_camera_through_the_first_steps_of_its_outage(recorded_steps, checkpoint):
    """The camera dies at step 6: with per-step presence the window after it still holds the camera
    (its last step absent, zeroed) and the forecast is the model's on that window; without, the
    camera is absent from the window at once."""
    steps = with_outages(recorded_steps, 1)[:7]
    per_step = ForecastTransform.from_checkpoint(checkpoint, per_step_presence=True)
    whole = ForecastTransform.from_checkpoint(checkpoint)
    out = replay(per_step, steps)[-1]
    replay(whole, steps)
    window = per_step.window()
    assert (
        window.get(keys.present_key("image")).all()
        and not whole.window().get(keys.present_key("image")).any()
    )
    assert window.get(keys.present_steps_key("image")).tolist() == [[True, True, False]]
    assert not window.get(keys.obs_key("image"))[:, -1].any()
    with torch.no_grad():
        expected = per_step.model(window.clone()).get(keys.FORECAST_LOC)
    torch.testing.assert_close(out[keys.FORECAST_LOC], per_step.normalizer.denormalize_target(expected))
    history = HistoryWindow(PUSH_SPECS, per_step.normalizer.stats, HISTORY, per_step_presence=True)
    replay(history, steps)
    assert torch.equal(
        history.window().get(keys.present_steps_key("image")), window.get(keys.present_steps_key("image"))
    )


@pytest.mark.parametrize("partial_windows", [True, False, None])
def test_a_transform_of_a_trained_run_counts_presence_as_the_run_was_trained(
    recorded_steps, tmp_path, partial_windows, caplog
):
    """A run trained with ``data.partial_windows=true`` is served windows that keep the camera
    through the first steps of its outage (per-step presence); one trained without (or before the
    key existed) windows that lose it at once. No warning: nothing contradicts the training."""
    path = write_checkpoint(tmp_path, PUSH_SPECS, partial_windows=partial_windows)
    steps = with_outages(recorded_steps, 1)[:7]  # the camera dies at the last step
    per_step = bool(partial_windows)
    model, stats, data_config = load_trained_model(path)
    history = HistoryWindow.for_model(model, stats, per_step_presence=per_step)
    with caplog.at_level(logging.WARNING, logger="mmf_rl.rl"):
        transforms = [
            ForecastTransform.from_checkpoint(path),
            LatchedForecastTransform.from_checkpoint(path),
            LatchedForecastTransform.for_trained(model, stats, data_config),
        ]
    assert not caplog.records
    for transform in [*transforms, history]:
        assert transform.per_step_presence is per_step
        replay(transform, steps)
        window = transform.window()
        assert window.get(keys.present_key("image")).tolist() == [per_step]
        assert (keys.present_steps_key("image") in window.keys(True)) is per_step


@pytest.mark.parametrize("partial_windows", [True, False])
def test_an_explicit_presence_rule_overrides_the_run_and_warns_when_it_contradicts_it(
    tmp_path, partial_windows, caplog
):
    path = write_checkpoint(tmp_path, PUSH_SPECS, partial_windows=partial_windows)
    with caplog.at_level(logging.WARNING, logger="mmf_rl.rl"):
        same = ForecastTransform.from_checkpoint(path, per_step_presence=partial_windows)
    assert same.per_step_presence is partial_windows and not caplog.records
    with caplog.at_level(logging.WARNING, logger="mmf_rl.rl"):
        other = LatchedForecastTransform.from_checkpoint(path, per_step_presence=not partial_windows)
    assert other.per_step_presence is (not partial_windows)
    (record,) = caplog.records
    assert f"per_step_presence={not partial_windows}" in record.getMessage()
    assert f"data.partial_windows={partial_windows}" in record.getMessage()


def test_the_recommended_preset_trains_and_forecasts_in_an_env(recorded_push_root, push_cache_dir, tmp_path):
    """``experiment=robust_mult`` (MulT trained for missing sensors) drops into the TorchRL env as the
    paper model does: trained by ``mmf-rl train``, loaded by ``ForecastTransform.from_checkpoint``."""
    from mmf_rl.cli import main as cli
    from tests.conftest import push_train_overrides

    run = tmp_path / "run"
    base = push_train_overrides(recorded_push_root, push_cache_dir, run, steps=3)
    sizes = ["model.d_model=16", "model.head_hidden=32", "model.num_heads=2", "model.mlp_hidden=32"]
    assert (
        cli(["train", "experiment=robust_mult", *(o for o in base if not o.startswith("model.")), *sizes])
        == 0
    )
    transform = ForecastTransform.from_checkpoint(run / "checkpoints", num_samples=2)
    assert transform.model.model_name == "mult"
    env = TransformedEnv(
        MultimodalPushTorchEnv(image_size=IMAGE_SIZE),
        Compose(ModalityDropout(["image", "force"], outage_prob=0.5, seed=0), transform),
    )
    try:
        rollout = env.rollout(4)
        assert rollout.get(keys.FORECAST_LOC).shape == (4, 3, 2)
        assert torch.isfinite(rollout.get(keys.FORECAST_LOC)).all()
    finally:
        env.close()
