from __future__ import annotations

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
from mmf_rl.rl.transforms import ForecastTransform, HistoryWindow
from tests.envs.conftest import IMAGE_SIZE
from tests.envs.stamp_env import MODALITIES, VECTOR_DIMS, stamp_envs

HISTORY, HORIZON, TARGET_DIM = 3, 4, 2
MODEL_IMAGE = 16  # smaller than the env's frames: the transform resizes them


def make_stats(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    stats = {}
    for name, dim in [*VECTOR_DIMS.items(), ("target", TARGET_DIM)]:
        stats[f"{name}/mean"] = torch.randn(dim, generator=g)
        stats[f"{name}/std"] = torch.rand(dim, generator=g) + 0.5
    return stats


def write_checkpoint(directory, specs, stride: int = 1):
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
        specs,
        HISTORY,
        HORIZON,
        TARGET_DIM,
    )
    save_checkpoint(
        directory,
        1,
        model.state_dict(),
        tensors=make_stats(),
        meta={
            "model_config": saved_config("forecaster", model),
            "config": {"data": {"history": HISTORY, "horizon": HORIZON, "stride": stride}},
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


def test_forecast_env_passes_check_env_specs(checkpoint):
    env = TransformedEnv(
        SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)),
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.3, seed=0),
            ForecastTransform.from_checkpoint(checkpoint, num_samples=3),
        ),
    )
    try:
        check_env_specs(env, seed=0)
        spec = env.observation_spec
        assert spec[keys.FORECAST_LOC].shape == (2, HORIZON, TARGET_DIM)
        assert spec[keys.FORECAST_SAMPLES].shape == (2, 3, HORIZON, TARGET_DIM)
    finally:
        env.close()


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


def test_forecast_equals_the_model_on_the_window_built_by_hand(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    model, normalizer = forecast.model, forecast.normalizer
    env = TransformedEnv(
        SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)),
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2),
            forecast,
        ),
    )
    try:
        env.set_seed(0)
        td = env.rollout(6, break_when_any_done=False)
    finally:
        env.close()
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


@pytest.mark.parametrize("num_envs", [1, 3])
def test_traced_forecast_equals_the_eager_forward(checkpoint, num_envs):
    """The lean path (one trace per batch size and presence pattern) writes the eager forward's forecasts."""

    def rollout(trace: bool):
        forecast = ForecastTransform.from_checkpoint(checkpoint, trace=trace)
        base = (
            MultimodalPushTorchEnv(image_size=IMAGE_SIZE)
            if num_envs == 1
            else SerialEnv(num_envs, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE))
        )
        env = TransformedEnv(
            base,
            Compose(
                ModalityDropout(["image", "force"], outage_prob=0.3, bursts=UniformBursts(1, 3), seed=4),
                forecast,
            ),
        )
        try:
            env.set_seed(0)
            torch.manual_seed(0)  # the random actions
            assert not env.reset()[keys.FORECAST_LOC].is_inference(), "a policy can train on the forecasts"
            return env.rollout(12, break_when_any_done=False), forecast
        finally:
            env.close()

    traced, forecast = rollout(trace=True)
    eager, _ = rollout(trace=False)
    patterns = {pattern[1:] for pattern in forecast._graphs}  # noqa: SLF001
    # Batch 1: every step is traced; a batch of 3 mixes presence across envs, so the eager path runs too.
    assert len(patterns) >= (2 if num_envs == 1 else 1), (
        "the rollout should exercise traced presence patterns"
    )
    for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
        torch.testing.assert_close(traced["next", *key], eager["next", *key])


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


def test_history_window_is_the_model_batch_built_by_hand(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    history = HistoryWindow.for_model(forecast.model, forecast.normalizer.stats)
    env = TransformedEnv(
        SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)),
        Compose(
            ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2), history
        ),
    )
    try:
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
    finally:
        env.close()
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
