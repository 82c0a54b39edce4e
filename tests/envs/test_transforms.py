from __future__ import annotations

import functools

import pytest
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import Compose, EnvBase, SerialEnv, TransformedEnv
from torchrl.envs.utils import check_env_specs

from mmf_rl import keys
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.envs.torchrl_env import MultimodalPushTorchEnv
from mmf_rl.envs.transforms import (
    ForecastTransform,
    GeometricBursts,
    HistoryWindow,
    ModalityDropout,
    UniformBursts,
    outage_start_prob,
    replay_outages,
)
from mmf_rl.keys import FORECAST_VALID, ModalitySpec
from mmf_rl.models import build_model, saved_config
from mmf_rl.trainers.checkpoint import save_checkpoint
from tests.envs.conftest import IMAGE_SIZE

HISTORY, HORIZON, TARGET_DIM = 3, 4, 2
MODEL_IMAGE = 16  # smaller than the env's frames: the transform resizes them
MODALITIES = ("image", "force", "proprio")
VECTOR_DIMS = {"force": 6, "proprio": 17}


class StampEnv(EnvBase):
    """The push env's observation layout, filled with a stamp of (env, episode, step).

    Every entry of ``("obs", m)`` at step ``t`` of episode ``e`` of env ``k`` holds
    ``stamp = 1000 * k + 100 * e + t + 1`` (images: ``stamp % 256``), so a window read back from a
    transform tells exactly which steps it holds.
    """

    def __init__(self, env_index: int = 0, max_steps: int = 1000):
        super().__init__(batch_size=torch.Size([]))
        self.env_index, self.max_steps = env_index, max_steps
        self.episode, self.t = -1, 0
        self.observation_spec = Composite({
            keys.OBS: Composite(image=Bounded(0, 255, (3, IMAGE_SIZE, IMAGE_SIZE), dtype=torch.uint8),
                                **{m: Unbounded((d,)) for m, d in VECTOR_DIMS.items()}),
            keys.PRESENT: Composite({m: Categorical(2, (), dtype=torch.bool) for m in MODALITIES}),
        })
        self.action_spec = Bounded(-1.0, 1.0, (1,))
        self.reward_spec = Unbounded((1,))

    def stamp(self) -> int:
        return 1000 * self.env_index + 100 * self.episode + self.t + 1

    def _observation(self) -> TensorDict:
        stamp = self.stamp()
        return TensorDict({
            keys.OBS: {"image": torch.full((3, IMAGE_SIZE, IMAGE_SIZE), stamp % 256, dtype=torch.uint8),
                       **{m: torch.full((d,), float(stamp)) for m, d in VECTOR_DIMS.items()}},
            keys.PRESENT: {m: torch.tensor(True) for m in MODALITIES},
        }, batch_size=[])

    def _reset(self, tensordict=None, **kwargs):
        self.episode, self.t = self.episode + 1, 0
        return self._observation().update({"done": torch.tensor([False]), "terminated": torch.tensor([False])})

    def _step(self, tensordict):
        self.t += 1
        done = torch.tensor([self.t >= self.max_steps])
        return self._observation().update({"reward": torch.zeros(1), "done": done, "terminated": done.clone()})

    def _set_seed(self, seed):
        pass


def stamp_envs(num_envs: int, max_steps: int = 1000) -> SerialEnv:
    return SerialEnv(num_envs, [functools.partial(StampEnv, k, max_steps) for k in range(num_envs)])


def make_stats(seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    stats = {}
    for name, dim in [*VECTOR_DIMS.items(), ("target", TARGET_DIM)]:
        stats[f"{name}/mean"] = torch.randn(dim, generator=g)
        stats[f"{name}/std"] = torch.rand(dim, generator=g) + 0.5
    return stats


def write_checkpoint(directory, specs, stride: int = 1):
    torch.manual_seed(0)
    model = build_model({"name": "forecaster", "d_model": 16, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32,
                         "head_hidden": 32}, specs, HISTORY, HORIZON, TARGET_DIM)
    save_checkpoint(directory, 1, model.state_dict(), tensors=make_stats(),
                    meta={"model_config": saved_config("forecaster", model),
                          "config": {"data": {"history": HISTORY, "horizon": HORIZON, "stride": stride}}})
    return directory


PUSH_SPECS = [
    ModalitySpec("image", "image", (3, MODEL_IMAGE, MODEL_IMAGE), encoder_kwargs={"channels": (8, 16)}),
    ModalitySpec("force", "sequence", (6,)),
    ModalitySpec("proprio", "sequence", (17,)),
]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return write_checkpoint(tmp_path_factory.mktemp("ckpt"), PUSH_SPECS)


# -- ModalityDropout -----------------------------------------------------------------------------


def dropout_rollout(dropout: ModalityDropout, num_envs: int = 4, steps: int = 120, max_steps: int = 1000):
    env = TransformedEnv(stamp_envs(num_envs, max_steps), dropout)
    try:
        return env.rollout(steps, break_when_any_done=False)
    finally:
        env.close()


def presence_over_time(td, name: str) -> torch.Tensor:
    """``[envs, steps + 1]``: the reset observation, then every step's."""
    return torch.cat([td[keys.present_key(name)][:, :1], td["next", keys.PRESENT, name]], dim=1)


def runs_of_absence(present: torch.Tensor) -> list[int]:
    """Lengths of the runs of False in each row, without runs cut by the rollout's ends."""
    lengths = []
    for row in present.tolist():
        run, started_inside = 0, False
        for i, p in enumerate(row):
            if not p:
                if run == 0:
                    started_inside = i > 0
                run += 1
            else:
                if run and started_inside:
                    lengths.append(run)
                run = 0
    return lengths


def test_dropout_zeroes_data_and_clears_presence():
    td = dropout_rollout(ModalityDropout(["image", "force"], outage_prob=0.2, bursts=UniformBursts(1, 4), seed=0))
    nxt = td["next"]
    for name in ("image", "force"):
        absent = ~nxt[keys.PRESENT, name]
        assert 0 < absent.float().mean() < 1
        obs = nxt[keys.obs_key(name)].flatten(2)
        assert (obs[absent] == 0).all(), "an absent modality carries zeros"
        assert (obs[~absent] != 0).all(), "a present modality keeps its data"
    assert nxt[keys.PRESENT, "proprio"].all(), "modalities not listed never fail"


def test_dropout_is_reproducible_from_its_seed_and_independent_per_env():
    def pattern(seed):
        td = dropout_rollout(ModalityDropout(["image", "force"], outage_prob=0.1, seed=seed), steps=60)
        return torch.stack([presence_over_time(td, m) for m in ("image", "force")])

    first = pattern(3)
    assert torch.equal(first, pattern(3))
    assert not torch.equal(first, pattern(4))
    assert not torch.equal(first[:, 0], first[:, 1]), "each env draws its own outages"


@pytest.mark.parametrize("bursts", [UniformBursts(2, 4), GeometricBursts(3.0)])
def test_dropout_bursts_have_the_configured_lengths(bursts):
    td = dropout_rollout(ModalityDropout(["force"], outage_prob=0.15, bursts=bursts, seed=1), num_envs=4, steps=300)
    lengths = torch.tensor(runs_of_absence(presence_over_time(td, "force")))
    assert len(lengths) > 40
    if isinstance(bursts, UniformBursts):
        assert set(lengths.tolist()) == {2, 3, 4}
    else:
        assert lengths.min() == 1 and lengths.max() > 6
        assert abs(lengths.float().mean().item() - 3.0) < 0.6


def test_replay_outages_gives_each_modality_its_measured_fraction_and_bursts():
    outages = {"force": {"fraction": 0.2, "mean_burst": 4.0}, "image": {"fraction": 0.05, "mean_burst": 2.0},
               "proprio": {"fraction": 0.0, "mean_burst": 0.0}}
    replay = replay_outages(outages, seed=3)
    assert [t.modalities for t in replay] == [["force"], ["image"]]  # nothing to replay for proprio
    td = dropout_rollout(replay, num_envs=4, steps=600)
    for name in ("force", "image"):
        present = presence_over_time(td, name)
        assert abs((~present).float().mean().item() - outages[name]["fraction"]) < 0.04, name
        lengths = torch.tensor(runs_of_absence(present)).float()
        assert abs(lengths.mean().item() - outages[name]["mean_burst"]) < 0.25 * outages[name]["mean_burst"], name
    assert presence_over_time(td, "proprio").all()
    assert outage_start_prob(0.2, 4.0) == pytest.approx(0.0625)  # 4 / (4 + 1 / p) = 0.2
    with pytest.raises(ValueError, match="no modality .* has outages to replay"):
        replay_outages({"proprio": outages["proprio"]})


def test_dropout_per_episode_holds_for_the_whole_episode():
    td = dropout_rollout(ModalityDropout(["image"], outage_prob=0.5, per="episode", seed=0),
                         num_envs=8, steps=40, max_steps=10)
    present = presence_over_time(td, "image")  # 4 episodes of 10 steps per env
    steps = torch.arange(present.shape[1])
    for env in range(present.shape[0]):
        for episode in range(4):
            # Step 10 of an episode is its terminal observation; the reset observation follows in the root td.
            chunk = present[env, (steps > 10 * episode) & (steps <= 10 * episode + 9)]
            assert chunk.all() or not chunk.any()
    assert 0 < present.float().mean() < 1


def test_dropout_reset_clears_the_outages_of_the_envs_that_reset():
    env = TransformedEnv(stamp_envs(2), ModalityDropout(["force"], outage_prob=1.0, bursts=UniformBursts(5, 5)))
    try:
        td = env.reset()
        # An outage starts at the reset observation: 5 absent observations, then one present.
        for _ in range(3):
            td = env.step(env.rand_action(td))["next"]
        td["_reset"] = torch.tensor([[True], [False]])
        td = env.reset(td)
        present = [td[keys.present_key("force")].tolist()]
        for _ in range(5):
            td = env.step(env.rand_action(td))["next"]
            present.append(td[keys.present_key("force")].tolist())
        # env 0 restarted its 5-step outage at the reset; env 1 finished its outage 2 steps later.
        assert [p[0] for p in present] == [False] * 5 + [True]
        assert [p[1] for p in present] == [False, False, True, False, False, False]
    finally:
        env.close()


# -- ForecastTransform ---------------------------------------------------------------------------


def test_forecast_env_passes_check_env_specs(checkpoint):
    env = TransformedEnv(SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)), Compose(
        ModalityDropout(["image", "force"], outage_prob=0.3, seed=0),
        ForecastTransform.from_checkpoint(checkpoint, num_samples=3),
    ))
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
            flat = F.interpolate(values.flatten(0, 1).float() / 255, size=size, mode="bilinear", antialias=True,
                                 align_corners=False)
            values = (flat * 255).round().clamp(0, 255).to(torch.uint8).view(*values.shape[:3], *size)
        else:
            values = normalizer.normalize(spec.name, values) * present[:, None, None]
        window.set(spec.obs_key, values)
        window.set(spec.present_key, present)
    return window


def test_forecast_equals_the_model_on_the_window_built_by_hand(checkpoint):
    forecast = ForecastTransform.from_checkpoint(checkpoint)
    model, normalizer = forecast.model, forecast.normalizer
    env = TransformedEnv(SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)), Compose(
        ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2),
        forecast,
    ))
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
        torch.testing.assert_close(td["next", keys.FORECAST, "loc"][:, t - 1],
                                   normalizer.denormalize_target(out[keys.FORECAST_LOC]))
        torch.testing.assert_close(td["next", keys.FORECAST, "scale"][:, t - 1],
                                   normalizer.denormalize_target_scale(out[keys.FORECAST_SCALE]))
    assert saw_absent, "the rollout should exercise windows with a missing modality"
    assert td["next", FORECAST_VALID].all()


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
    env = TransformedEnv(stamp_envs(2), Compose(
        ModalityDropout(list(MODALITIES), outage_prob={"image": 1.0, "force": 1.0, "proprio": 0.0}, per="episode"),
        forecast,
    ))
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


@pytest.mark.parametrize("specs,problem", [
    ([ModalitySpec("wrist", "image", (3, 16, 16), encoder_kwargs={"channels": (8, 16)})], "'wrist' is not emitted"),
    ([ModalitySpec("proprio", "sequence", (20,))], "'proprio' is float32 [17], expected float [20]"),
    ([ModalitySpec("image", "image", (1, 16, 16), encoder_kwargs={"channels": (8, 16)})], "expected uint8 [1, h, w]"),
])
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
    env = TransformedEnv(SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)), Compose(
        ModalityDropout(["image", "force"], outage_prob=0.25, bursts=UniformBursts(1, 3), seed=2), history))
    try:
        check_env_specs(env, seed=0)
        assert env.observation_spec[keys.HISTORY, keys.OBS, "image"].shape == (2, HISTORY, 3, MODEL_IMAGE, MODEL_IMAGE)
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
    model = build_model({"name": "forecaster", "d_model": 16, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32,
                         "head_hidden": 32}, PUSH_SPECS, HISTORY, HORIZON, TARGET_DIM, action_shape=(HORIZON, 4))
    with pytest.raises(ValueError, match="action-conditioned world model.*HistoryWindow.*SequenceCEMPlanner"):
        ForecastTransform(model, make_stats())
