"""Behaviour cloning from the recorded push data, with and without the forecaster's forecast as input."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, InitTracker, SerialEnv, TransformedEnv
from torchrl.envs.utils import step_mdp

from benchmarks.push.bc_evaluation import bc_env
from benchmarks.push.dagger import EXPERT_ACTION, demonstration_frames, labelled_episodes
from benchmarks.push.outage_evaluation import Condition
from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.envs.modality_dropout import ModalityDropout
from mmf_rl.envs.torchrl_env import GOAL, OBJECT_POSE, MultimodalPushTorchEnv
from mmf_rl.rl import (
    BCPolicy,
    DemonstrationLoader,
    Demonstrations,
    EncoderChoice,
    ForecastTable,
    ForecastTransform,
    HistoryWindow,
    train_bc,
    validation_errors,
)
from mmf_rl.rl.action_chunks import ACTION_CHUNK, PAST_CHUNKS, PAST_CHUNKS_FILLED
from mmf_rl.rl.bc import BCConfig
from mmf_rl.rl.demonstrations import DEMONSTRATED_CHUNK, DEMONSTRATED_CHUNK_MASK
from mmf_rl.rl.latched_forecast import LatchedForecastTable, LatchedForecastTransform
from mmf_rl.trainers.trainer import TrainerConfig, seed_everything
from tests.rl.test_action_chunks import act_ensemble

IMAGE_SIZE = 32  # as recorded by `recorded_push_root`
DROPPABLE = ("image", "force")
TINY = {"d_model": 16, "hidden": 32, "depth": 1}
TINY_ENCODERS = EncoderChoice(image_channels=(8, 16))


def make_policy(
    demonstrations, forecasts=None, seed: int = 0, privileged_object: bool = False, **options
) -> BCPolicy:
    seed_everything(seed)
    return BCPolicy.for_demonstrations(
        demonstrations,
        forecasts,
        encoders=TINY_ENCODERS,
        privileged_object=privileged_object,
        **TINY,
        **options,
    )


def batch_with_forecasts(demonstrations, forecasts, frames: torch.Tensor, absent: dict) -> TensorDict:
    """The demonstrations' batch of ``frames`` under the outage ``absent``, with their forecasts."""
    batch = demonstrations.batch(frames, absent)
    loc, scale = forecasts.lookup(frames, absent)
    batch.update({keys.FORECAST_LOC: loc, keys.FORECAST_SCALE: scale})
    return batch


def recorded_steps(demonstrations, frames: torch.Tensor, image_absent: bool) -> list[TensorDict]:
    """The recorded frames as the env's per-step observations (single frames, presence flags)."""
    steps = list(demonstrations.env_observation(frames).unbind(0))
    if image_absent:
        for step in steps:
            step.get(keys.obs_key("image")).zero_()
            step.set(keys.present_key("image"), torch.tensor(False))
    return steps


def test_demonstrations_hold_every_frame_with_goal_and_action(demonstrations, recorded_push_root):
    n = sum(len(f) for f in demonstrations.split_frames.values())
    assert n == len(demonstrations.goal) == len(demonstrations.action)  # every frame, the first ones too
    assert demonstrations.goal.shape[1] == 3 and demonstrations.action.shape[1] == 4
    assert torch.isfinite(demonstrations.action).all() and demonstrations.action.abs().max() <= 1
    train = demonstrations.split_frames["train"]
    batch = demonstrations.batch(train[:5])
    h = demonstrations.history
    assert batch.get((keys.HISTORY, "obs", "image")).shape == (5, h, 3, IMAGE_SIZE, IMAGE_SIZE)
    assert batch.get((keys.HISTORY, "obs", "proprio")).shape == (5, h, 17)
    assert batch.get(GOAL).shape == (5, 3) and batch.get("action").shape == (5, 4)


def test_offline_windows_and_forecasts_are_what_the_transforms_build_online(
    demonstrations, forecasts, forecaster
):
    """Stepping `HistoryWindow` and `ForecastTransform` through a recorded episode (with the camera
    on, then off for the whole episode) gives the windows and forecasts the policy trains on."""
    model, stats, _ = forecaster
    frames = demonstrations.split_frames["train"]
    episode = frames[: demonstrations.history + 3]  # the first frames of the first episode: padded windows
    assert bool((demonstrations._episode_start[episode] == episode[0]).all())
    for image_absent, drop_index in [(False, 0), (True, 1)]:
        history = HistoryWindow(demonstrations.specs, demonstrations.normalizer.stats, demonstrations.history)
        forecast = ForecastTransform(model, stats, denormalize=False)
        absent = {"image": torch.full((len(episode),), image_absent)}
        expected = demonstrations.window(episode, absent)
        for t, step in enumerate(recorded_steps(demonstrations, episode, image_absent)):
            out = history.observe_reset(step.clone()) if t == 0 else history.observe_step(step.clone())
            out = forecast.observe_reset(out) if t == 0 else forecast.observe_step(out)
            window = out.get(keys.HISTORY)
            for spec in demonstrations.specs:
                present = bool(expected.get(spec.present_key)[t])
                assert (
                    bool(window.get(spec.present_key))
                    == present
                    == (spec.name != "image" or not image_absent)
                )
                if present:  # what an absent sensor holds is never read
                    torch.testing.assert_close(window.get(spec.obs_key), expected.get(spec.obs_key)[t])
            torch.testing.assert_close(out.get(keys.FORECAST_LOC), forecasts.loc[episode[t], drop_index])
            torch.testing.assert_close(out.get(keys.FORECAST_SCALE), forecasts.scale[episode[t], drop_index])


def test_a_forecaster_trained_on_partial_windows_gets_them_offline_and_online(demonstrations, forecaster):
    """For a forecaster trained with ``data.partial_windows=true``, an episode whose camera dies at
    step 6 (added to the demonstrations) keeps the camera in the windows of the next H-1 steps,
    and the table computed offline is what `bc_env`'s `ForecastTransform` serves online; a run
    trained without partial windows loses the camera at once, offline and online alike."""
    model, stats, data_config = forecaster
    dies, h = 6, demonstrations.history
    frames = demonstrations.split_frames["train"][: dies + h]
    steps = recorded_steps(demonstrations, frames, image_absent=False)
    for step in steps[dies:]:
        step.get(keys.obs_key("image")).zero_()
        step.set(keys.present_key("image"), torch.tensor(False))
    episode = torch.stack(steps)
    episode.set(GOAL, demonstrations.goal[frames])
    episode.set("action", demonstrations.action[frames])
    added = demonstrations.with_episodes([episode])
    rows = torch.arange(len(demonstrations.goal), len(added.goal))
    tables = {}
    for partial in (True, False):
        trained = {**data_config, "partial_windows": partial}
        table = ForecastTable.for_trained(added, model, stats, trained, DROPPABLE, frames=rows)
        online = ForecastTransform.for_trained(model, stats, trained, denormalize=False)
        assert table.per_step_presence is online.per_step_presence is partial
        served = [online.observe_reset(steps[0].clone())] + [
            online.observe_step(s.clone()) for s in steps[1:]
        ]
        for t, out in enumerate(served):
            torch.testing.assert_close(out.get(keys.FORECAST_LOC), table.loc[rows[t], 0])
            torch.testing.assert_close(out.get(keys.FORECAST_SCALE), table.scale[rows[t], 0])
        window = added.window(rows, specs=model.config.modalities, per_step_presence=partial)
        assert window.get(keys.present_key("image"))[dies : dies + h - 1].all() == partial
        tables[partial] = table.loc[rows, 0]
    torch.testing.assert_close(tables[True][:dies], tables[False][:dies])  # the camera at every step
    assert not torch.allclose(tables[True][dies], tables[False][dies])


@pytest.mark.parametrize("partial_windows", [True, False])
def test_bc_env_serves_forecasts_with_the_presence_rule_the_forecaster_was_trained_on(
    demonstrations, forecasts, forecaster, partial_windows
):
    model, stats, data_config = forecaster
    trained = (model, stats, {**data_config, "partial_windows": partial_windows})
    env = bc_env(make_policy(demonstrations, forecasts), trained, IMAGE_SIZE, Condition("all", None, None), 0)
    try:
        (forecast,) = [t for t in env.transform if isinstance(t, ForecastTransform)]
        assert forecast.per_step_presence is partial_windows
    finally:
        env.close()


def test_dropout_draws_are_seeded_and_never_remove_every_sensor(demonstrations):
    def draws(seed):
        loader = DemonstrationLoader(
            demonstrations, "train", 16, dropout={"image": 0.5, "force": 0.5, "proprio": 0.9}, seed=seed
        )
        return [
            torch.stack([b.get((keys.HISTORY, *s.present_key)) for s in demonstrations.specs]) for b in loader
        ]

    first, again, other = draws(0), draws(0), draws(1)
    assert all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    assert not all(torch.equal(a, b) for a, b in zip(first, other, strict=True))
    present = torch.cat(first, 1)
    assert present.any(0).all()  # every sample keeps a sensor
    assert (~present).any(1).all()  # and each modality is removed from some


def test_the_absent_modality_never_changes_the_action(demonstrations, forecasts):
    policy = make_policy(demonstrations, forecasts).eval()
    frames = demonstrations.split_frames["train"][:6]
    batch = batch_with_forecasts(
        demonstrations, forecasts, frames, {"image": torch.ones(6, dtype=torch.bool)}
    )
    action = policy(batch.clone()).get("action")
    garbage = batch.clone()
    image = garbage.get((keys.HISTORY, "obs", "image"))
    garbage.set((keys.HISTORY, "obs", "image"), torch.randint_like(image, 0, 256))
    torch.testing.assert_close(policy(garbage).get("action"), action)
    assert torch.isfinite(action).all()


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_policy_acts_in_the_push_env_with_a_sensor_off(demonstrations, forecasts, forecaster, with_forecasts):
    model, stats, _ = forecaster
    policy = make_policy(demonstrations, forecasts if with_forecasts else None).eval()
    forecast = ForecastTransform(model, stats, denormalize=False) if with_forecasts else None
    env = TransformedEnv(
        MultimodalPushTorchEnv(image_size=IMAGE_SIZE),
        Compose(ModalityDropout(["image"], outage="episode", outage_prob=1.0), *policy.transforms(forecast)),
    )
    try:
        env.set_seed(0)
        with torch.no_grad():
            rollout = env.rollout(4, policy, break_when_any_done=False)
    finally:
        env.close()
    h = demonstrations.history
    assert rollout.get((keys.HISTORY, "obs", "image")).shape == (4, h, 3, IMAGE_SIZE, IMAGE_SIZE)
    assert rollout.get((keys.HISTORY, "obs", "force")).shape == (4, h, 6)
    assert not rollout.get((keys.HISTORY, "present", "image")).any()
    assert rollout.get((keys.HISTORY, "present", "proprio")).all()
    action = rollout.get("action")
    assert action.shape == (4, 4) and torch.isfinite(action).all() and action.abs().max() <= 1
    assert (keys.FORECAST_LOC in rollout.keys(True)) == with_forecasts
    if with_forecasts:
        assert rollout.get(keys.FORECAST_LOC).shape == (4, *forecasts.shape)


@pytest.mark.parametrize("with_forecasts", [False, True])
def test_training_reduces_the_bc_loss_on_recorded_pushes(demonstrations, forecasts, with_forecasts, tmp_path):
    table = forecasts if with_forecasts else None
    policy = make_policy(demonstrations, table)
    before = validation_errors(policy, demonstrations, "train", DROPPABLE, table)["loss"]
    config = TrainerConfig(
        total_steps=40,
        batch_size=32,
        lr=3e-3,
        lr_schedule="constant",
        warmup_steps=1,
        eval_every=40,
        checkpoint_every=40,
        progress_bar=False,
    )
    metrics = train_bc(policy, demonstrations, config, forecasts=table, run_dir=tmp_path)
    after = validation_errors(policy, demonstrations, "train", DROPPABLE, table)["loss"]
    assert after < 0.8 * before, (before, after)
    assert {
        "val/loss",
        "val/mse_all",
        "val/mse_no_image",
        "val/mse_no_force",
        "val/mse_no_image_force",
    } <= set(metrics)
    # The run's checkpoint is the trained policy.
    loaded = BCPolicy.from_checkpoint(tmp_path / "checkpoints")
    assert validation_errors(loaded, demonstrations, "train", DROPPABLE, table)["loss"] == pytest.approx(
        after
    )


def test_save_and_load_round_trip(demonstrations, forecasts, push_forecaster_run, tmp_path):
    policy = make_policy(demonstrations, forecasts, seed=3).eval()
    policy.save(tmp_path / "policy")
    loaded = BCPolicy.from_checkpoint(tmp_path / "policy")
    assert loaded.config == policy.config
    assert loaded.stats.keys() == policy.stats.keys()
    frames = demonstrations.split_frames["val"][:4]
    batch = batch_with_forecasts(
        demonstrations, forecasts, frames, {"force": torch.tensor([True, False, True, False])}
    )
    torch.testing.assert_close(loaded(batch.clone()).get("action"), policy(batch.clone()).get("action"))
    with pytest.raises(CheckpointError, match="not a behaviour-cloning policy"):
        BCPolicy.from_checkpoint(push_forecaster_run / "checkpoints")


def test_transforms_refuse_a_forecast_the_policy_was_not_trained_with(demonstrations, forecasts, forecaster):
    model, stats, _ = forecaster
    with_forecasts, without = make_policy(demonstrations, forecasts), make_policy(demonstrations)
    with pytest.raises(ValueError, match="reads forecasts of shape"):
        with_forecasts.transforms()
    with pytest.raises(ValueError, match="denormalize=False"):
        with_forecasts.transforms(ForecastTransform(model, stats))
    with pytest.raises(ValueError, match="trained without forecasts"):
        without.transforms(ForecastTransform(model, stats, denormalize=False))
    with pytest.raises(ValueError, match="pass the ForecastTable"):
        train_bc(with_forecasts, demonstrations, TrainerConfig(total_steps=1, progress_bar=False))


def test_a_forecast_table_shorter_than_the_demonstrations_is_refused(demonstrations, forecasts):
    short = ForecastTable(forecasts.loc[:10], forecasts.scale[:10], forecasts.droppable)
    policy = make_policy(demonstrations, short)
    with pytest.raises(ValueError, match="covers 10 frames.*ForecastTable.extended"):
        train_bc(policy, demonstrations, TrainerConfig(total_steps=1, progress_bar=False), forecasts=short)


def test_stats_without_the_goals_are_named(demonstrations):
    stats = {k: v for k, v in demonstrations.normalizer.stats.items() if not k.startswith(f"{GOAL}/")}
    with pytest.raises(KeyError, match=r"BCNetwork: normalisation stats lack \['goal/mean', 'goal/std'\]"):
        BCPolicy(make_policy(demonstrations).config, stats)


def test_a_forecast_table_refuses_a_world_model(demonstrations, push_world_model):
    with pytest.raises(ValueError, match="action-conditioned world model"):
        ForecastTable.compute(
            demonstrations, push_world_model.model, push_world_model.normalizer.stats, DROPPABLE
        )


def test_a_goal_or_action_feature_the_recording_lacks_is_named(forecaster):
    _, _, data_config = forecaster
    data = WindowDataset(DataConfig.from_dict(data_config))
    with pytest.raises(ValueError, match="no vector feature 'observation.gaol'.*observation.goal"):
        Demonstrations(data, goal_feature="observation.gaol")
    with pytest.raises(ValueError, match="no vector feature 'observation.images.front'"):
        Demonstrations(data, action_feature="observation.images.front")


# -- the latched forecast as an input ---------------------------------------------------------------


@pytest.fixture(scope="module")
def latched_forecasts(demonstrations, forecasts, forecaster) -> LatchedForecastTable:
    return LatchedForecastTable.for_trained(forecasts, demonstrations, *forecaster)


def test_offline_latched_forecasts_are_what_the_latched_transform_serves_online(
    demonstrations, latched_forecasts, forecaster
):
    """Stepping `LatchedForecastTransform` through a recorded episode whose camera dies at step 6
    serves, at each step, the table's forecast for that frame with the latch's age."""
    model, stats, data_config = forecaster
    assert latched_forecasts.relative, "the push forecaster's target is relative: the re-basing is exercised"
    dies = 6
    episode = demonstrations.split_frames["train"][: dies + 8]
    online = LatchedForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    steps = recorded_steps(demonstrations, episode, image_absent=False)
    for step in steps[dies:]:
        step.get(keys.obs_key("image")).zero_()
        step.set(keys.present_key("image"), torch.tensor(False))
    served = [online.observe_reset(steps[0])] + [online.observe_step(s) for s in steps[1:]]
    camera_out = torch.arange(len(episode)) >= dies
    ages = torch.where(camera_out, torch.arange(len(episode)) - (dies - 1), 0)
    loc, scale, age = latched_forecasts.served(episode, {"image": camera_out}, ages)
    for t, out in enumerate(served):
        torch.testing.assert_close(out.get(keys.FORECAST_LOC), loc[t], msg=lambda m, t=t: f"step {t}: {m}")
        torch.testing.assert_close(
            out.get(keys.FORECAST_SCALE), scale[t], msg=lambda m, t=t: f"step {t}: {m}"
        )
        assert out.get(keys.FORECAST_AGE).item() == age[t].item() == ages[t].item()


def test_latch_ages_are_drawn_within_the_episode_for_the_samples_without_a_camera(
    demonstrations, latched_forecasts
):
    frames = demonstrations.split_frames["train"]
    camera_out = torch.rand(len(frames), generator=torch.Generator().manual_seed(123)) < 0.5

    def draw(seed: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(seed)
        return latched_forecasts.draw_ages(frames, {"image": camera_out}, generator)

    ages = draw(0)
    assert torch.equal(ages, draw(0)) and not torch.equal(ages, draw(1))
    assert not ages[~camera_out].any(), "a sample with its camera has a fresh forecast"
    since_start = frames - demonstrations.episode_start(frames)
    assert bool((ages <= since_start.clamp(max=latched_forecasts.max_age)).all())
    never = (ages[camera_out] == 0).float().mean().item()
    assert 0.1 < never < 0.4, "about never_latched (and the episodes' first frames) have no latch"


def test_a_policy_on_latched_forecasts_reads_their_age_and_acts_through_a_dying_camera(
    demonstrations, forecasts, latched_forecasts, forecaster, tmp_path
):
    model, stats, data_config = forecaster
    policy = make_policy(demonstrations, latched_forecasts)
    assert policy.config.latched_forecast == "precision" and keys.FORECAST_AGE in policy.in_keys
    config = TrainerConfig(total_steps=4, batch_size=16, eval_every=4, checkpoint_every=4, progress_bar=False)
    metrics = train_bc(policy, demonstrations, config, forecasts=latched_forecasts, run_dir=tmp_path)
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
    loaded = BCPolicy.from_checkpoint(tmp_path / "checkpoints")
    assert loaded.config == policy.config
    with pytest.raises(ValueError, match="reads the latched forecast"):
        policy.transforms(ForecastTransform(model, stats, denormalize=False))
    with pytest.raises(ValueError, match="not a LatchedForecastTransform"):
        make_policy(demonstrations, forecasts).transforms(
            LatchedForecastTransform.for_trained(model, stats, data_config, denormalize=False)
        )
    with pytest.raises(ValueError, match="the table serves rule precision"):
        train_bc(make_policy(demonstrations, forecasts), demonstrations, config, forecasts=latched_forecasts)
    env = bc_env(loaded.eval(), forecaster, IMAGE_SIZE, Condition("dies", "image", "dies"), seed=0)
    try:
        env.set_seed(0)
        with torch.no_grad():
            rollout = env.rollout(50, loaded, break_when_any_done=False)
    finally:
        env.close()
    age = rollout.get(("next", *keys.FORECAST_AGE))
    assert age.max() > 0, "the camera died: the latch serves and ages"
    assert torch.isfinite(rollout.get("action")).all()


# -- the forecast's first steps only ----------------------------------------------------------------


def test_a_policy_reading_the_first_forecast_steps_ignores_the_rest_and_round_trips(
    demonstrations, forecasts, tmp_path
):
    policy = make_policy(demonstrations, forecasts, forecast_steps=1).eval()
    whole = make_policy(demonstrations, forecasts).eval()
    horizon, dim = forecasts.shape
    assert policy.config.forecast_read_shape == (1, dim)
    assert whole.config.forecast_read_shape == (horizon, dim)
    head_inputs = policy.module.head[0].in_features
    assert whole.module.head[0].in_features - head_inputs == 2 * (horizon - 1) * dim

    frames = demonstrations.split_frames["train"][:6]
    batch = batch_with_forecasts(
        demonstrations, forecasts, frames, {"image": torch.ones(6, dtype=torch.bool)}
    )
    action = policy(batch.clone()).get("action")
    later, first = batch.clone(), batch.clone()
    later.get(keys.FORECAST_LOC)[:, 1:] += 1.0
    later.get(keys.FORECAST_SCALE)[:, 1:] *= 3.0
    first.get(keys.FORECAST_LOC)[:, 0] += 1.0
    torch.testing.assert_close(policy(later).get("action"), action)
    assert not torch.allclose(policy(first).get("action"), action)
    assert not torch.allclose(whole(later.clone()).get("action"), whole(batch.clone()).get("action"))

    policy.save(tmp_path / "policy")
    loaded = BCPolicy.from_checkpoint(tmp_path / "policy")
    assert loaded.config == policy.config
    torch.testing.assert_close(loaded(batch.clone()).get("action"), action)


def test_forecast_steps_outside_the_forecast_are_refused(demonstrations, forecasts):
    horizon = forecasts.shape[0]
    with pytest.raises(ValueError, match=rf"between 1 and the forecast's horizon \({horizon}"):
        make_policy(demonstrations, forecasts, forecast_steps=horizon + 1)
    with pytest.raises(ValueError, match="None: no forecast input"):
        make_policy(demonstrations, forecast_steps=1)


# -- the object's true position as an input (a diagnostic) -----------------------------------------


def test_a_privileged_policy_reads_the_objects_planar_position_and_an_ordinary_one_does_not(demonstrations):
    frames = demonstrations.split_frames["train"][:6]
    batch = demonstrations.batch(frames, {"image": torch.ones(6, dtype=torch.bool)})
    torch.testing.assert_close(batch.get(OBJECT_POSE), demonstrations.object_pose[frames])
    moved, turned = batch.clone(), batch.clone()
    moved.get(OBJECT_POSE)[:, 0] += 0.05  # 5 cm along x
    turned.get(OBJECT_POSE)[:, 3:] = torch.tensor([0.0, 0.0, 0.0, 1.0])  # another orientation

    privileged = make_policy(demonstrations, privileged_object=True).eval()
    assert privileged.config.privileged_object and OBJECT_POSE in privileged.in_keys
    action = privileged(batch.clone()).get("action")
    assert not torch.allclose(privileged(moved).get("action"), action)
    torch.testing.assert_close(privileged(turned.clone()).get("action"), action)  # the position only

    ordinary = make_policy(demonstrations).eval()
    assert not ordinary.config.privileged_object and OBJECT_POSE not in ordinary.in_keys
    torch.testing.assert_close(ordinary(moved.clone()).get("action"), ordinary(batch.clone()).get("action"))


def test_without_the_option_a_policy_keeps_its_parameters_and_an_old_checkpoint_loads(
    demonstrations, tmp_path
):
    ordinary = make_policy(demonstrations, seed=5).eval()
    privileged = make_policy(demonstrations, seed=5, privileged_object=True).eval()
    mine, theirs = ordinary.state_dict(), privileged.state_dict()
    assert set(theirs) - set(mine) == {"module.object_mean", "module.object_std"}
    first_layer = next(k for k in mine if k.startswith("module.head.") and k.endswith("weight"))
    for name, value in mine.items():
        if name == first_layer:  # two more inputs
            assert theirs[name].shape == (value.shape[0], value.shape[1] + 2)
        else:
            assert theirs[name].shape == value.shape, name
        if name.startswith("module.encoders."):  # drawn before the head, from the same seed
            assert torch.equal(theirs[name], value), name
    assert ordinary.in_keys == privileged.in_keys[:-1]

    # A checkpoint written before the option existed (no 'privileged_object' in its config).
    path = ordinary.save(tmp_path / "old")
    meta = json.loads((path / "meta.json").read_text())
    del meta["bc_config"]["privileged_object"]
    (path / "meta.json").write_text(json.dumps(meta))
    loaded = BCPolicy.from_checkpoint(tmp_path / "old")
    assert loaded.config == ordinary.config and loaded.in_keys == ordinary.in_keys
    batch = demonstrations.batch(demonstrations.split_frames["val"][:4])
    torch.testing.assert_close(loaded(batch.clone()).get("action"), ordinary(batch.clone()).get("action"))


def test_a_checkpoint_of_the_time_the_config_named_its_head_loads_as_the_regression_policy(
    demonstrations, tmp_path
):
    """``action_head: "mse"`` and ``gmm_components`` in a checkpoint's config (written while the package
    had the mixture head, now benchmarks/push/gmm_head.py's) are the regression policy's; a mixture's
    config is refused."""
    policy = make_policy(demonstrations, seed=3).eval()
    path = policy.save(tmp_path / "old")
    meta = json.loads((path / "meta.json").read_text())
    meta["bc_config"] |= {"action_head": "mse", "gmm_components": 5}
    (path / "meta.json").write_text(json.dumps(meta))
    loaded = BCPolicy.from_checkpoint(tmp_path / "old")
    assert loaded.config == policy.config and loaded.mode is None and loaded.out_keys == ["action"]
    batch = demonstrations.batch(demonstrations.split_frames["val"][:4])
    torch.testing.assert_close(loaded(batch.clone()).get("action"), policy(batch.clone()).get("action"))
    meta["bc_config"]["action_head"] = "gmm"
    (path / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="unknown keys \\['action_head', 'gmm_components'\\]"):
        BCPolicy.from_checkpoint(tmp_path / "old")


def test_a_privileged_policy_trains_and_its_offline_batches_are_what_it_read_online(
    demonstrations, forecaster, tmp_path
):
    """Frames the trained policy played (camera in bursts) and then added as demonstrations give,
    offline, the actions it took online: the same windows and the same object pose."""
    policy = make_policy(demonstrations, privileged_object=True)
    config = TrainerConfig(total_steps=4, batch_size=16, eval_every=4, checkpoint_every=4, progress_bar=False)
    train_bc(policy, demonstrations, config, run_dir=tmp_path)
    policy = BCPolicy.from_checkpoint(tmp_path / "checkpoints")
    assert policy.config.privileged_object
    env = bc_env(policy, forecaster, IMAGE_SIZE, Condition("bursts", "image", "bursts"), seed=0)
    try:
        (rollout, _), *_ = labelled_episodes(env, policy, 1, seed=0, max_steps=12)
    finally:
        env.close()
    assert not rollout.get((keys.HISTORY, "present", "image")).all(), "the camera was out at some steps"
    aggregated = demonstrations.with_episodes([demonstration_frames(rollout, demonstrations.specs)])
    played = torch.arange(len(demonstrations.goal), len(aggregated.goal))
    batch = aggregated.batch(played)
    torch.testing.assert_close(batch.get(OBJECT_POSE), rollout.get(OBJECT_POSE))
    with torch.no_grad():
        torch.testing.assert_close(policy(batch).get("action"), rollout.get("action"))


def test_a_privileged_policy_refuses_frames_without_the_object_pose(demonstrations, forecaster, tmp_path):
    _, _, data_config = forecaster
    blind = Demonstrations(WindowDataset(DataConfig.from_dict(data_config)), object_feature=None)
    assert blind.object_pose is None and OBJECT_POSE not in blind.batch(blind.split_frames["train"][:2])
    with pytest.raises(ValueError, match="object_feature='observation.object_pose'"):
        make_policy(blind, privileged_object=True)
    # Episodes saved before the pose was kept (an older DAgger round) train ordinary policies only.
    frames = demonstrations.split_frames["train"][:5]
    old = TensorDict(
        {GOAL: demonstrations.goal[frames], "action": demonstrations.action[frames]}, batch_size=[5]
    )
    for spec in demonstrations.specs:
        old.set(spec.obs_key, demonstrations.observation(spec.name, frames))
        old.set(spec.present_key, demonstrations._present[spec.name][frames])
    aggregated = demonstrations.with_episodes([old])
    assert aggregated.object_pose[-5:].isnan().all()
    make_policy(aggregated)
    with pytest.raises(ValueError, match="'train' frames have no object pose"):
        make_policy(aggregated, privileged_object=True)
    config = TrainerConfig(total_steps=1, progress_bar=False)
    with pytest.raises(ValueError, match="'train' frames have no object pose"):
        train_bc(make_policy(demonstrations, privileged_object=True), aggregated, config, run_dir=tmp_path)


# -- action chunks with temporal ensembling ----------------------------------------------------------

TINY_TRAINING = TrainerConfig(
    total_steps=4, batch_size=16, eval_every=4, checkpoint_every=4, progress_bar=False
)


def test_chunk_targets_are_the_next_actions_of_the_episode_masked_past_its_end(demonstrations):
    k = 4
    frames = demonstrations.split_frames["train"]
    first_episode = frames[demonstrations.episode_start(frames) == demonstrations.episode_start(frames[:1])]
    last = int(first_episode.max())
    assert int(demonstrations.episode_start(torch.tensor([last + 1]))) == last + 1, "another episode follows"
    queried = torch.arange(last - 5, last + 1)
    actions, mask = demonstrations.action_chunks(queried, k)
    assert actions.shape == (6, k, demonstrations.action_dim) and mask.shape == (6, k)
    for b, frame in enumerate(queried.tolist()):
        for i in range(k):
            inside = frame + i <= last
            assert bool(mask[b, i]) == inside
            expected = demonstrations.action[frame + i] if inside else torch.zeros(demonstrations.action_dim)
            torch.testing.assert_close(actions[b, i], expected)
    assert mask[-1].tolist() == [True, False, False, False]

    chunked = next(iter(DemonstrationLoader(demonstrations, "train", 8, action_chunk=k, shuffle=False)))
    torch.testing.assert_close(chunked.get(DEMONSTRATED_CHUNK)[:, 0], chunked.get("action"))
    assert chunked.get(DEMONSTRATED_CHUNK_MASK)[:, 0].all()
    plain = next(iter(DemonstrationLoader(demonstrations, "train", 8, shuffle=False)))
    assert DEMONSTRATED_CHUNK not in plain.keys() and DEMONSTRATED_CHUNK_MASK not in plain.keys()


def test_one_action_per_step_is_the_policy_of_a_config_without_chunks(demonstrations, tmp_path):
    """k = 1 (the default) builds, acts and trains bit for bit as a config written before chunks
    existed: same weights, outputs, transforms and training."""
    explicit = make_policy(demonstrations, seed=7, action_chunk=1, chunk_decay=0.01)
    old = explicit.config.to_dict()
    del old["action_chunk"], old["chunk_decay"]
    seed_everything(7)
    before = BCPolicy(BCConfig.from_dict(old), demonstrations.normalizer.stats)
    assert before.config == explicit.config and before.out_keys == explicit.out_keys == ["action"]
    assert explicit.ensemble is None and explicit.predictor() is explicit
    assert [type(t) for t in explicit.transforms()] == [HistoryWindow]
    mine, theirs = explicit.state_dict(), before.state_dict()
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    batch = demonstrations.batch(demonstrations.split_frames["val"][:4])
    acted = [policy.eval()(batch.clone()).get("action") for policy in (explicit, before)]
    assert torch.equal(*acted)
    metrics = [
        train_bc(policy.train(), demonstrations, TINY_TRAINING, run_dir=tmp_path / name)
        for name, policy in (("explicit", explicit), ("before", before))
    ]
    assert metrics[0] == metrics[1]
    assert all(torch.equal(v, before.state_dict()[k]) for k, v in explicit.state_dict().items())


def test_a_chunk_policy_trains_acts_with_the_ensemble_in_bc_env_and_its_dagger_frames_give_chunks(
    demonstrations, forecasts, forecaster, tmp_path
):
    k = 4
    policy = make_policy(demonstrations, forecasts, action_chunk=k)
    assert policy.out_keys == [ACTION_CHUNK] and policy.ensemble.chunk == k
    metrics = train_bc(policy, demonstrations, TINY_TRAINING, forecasts=forecasts, run_dir=tmp_path)
    assert all(torch.isfinite(torch.tensor(v)) for v in metrics.values())
    loaded = BCPolicy.from_checkpoint(tmp_path / "checkpoints")
    env = bc_env(loaded, forecaster, IMAGE_SIZE, Condition("bursts", "image", "bursts"), seed=0)
    try:
        assert sum(isinstance(t, InitTracker) for t in env.transform) == 1
        ((rollout, _),) = list(labelled_episodes(env, loaded, 1, seed=0, max_steps=12))
    finally:
        env.close()
    steps = rollout.shape[0]
    assert rollout.get("is_init").squeeze(-1).tolist() == [True] + [False] * (steps - 1)
    filled = rollout.get(PAST_CHUNKS_FILLED).sum(-1)
    assert filled.tolist() == [min(t, k - 1) for t in range(steps)]  # empty at the reset, then fills
    chunks = rollout.get(ACTION_CHUNK)
    assert chunks.shape == (steps, k, 4)
    torch.testing.assert_close(rollout.get("action"), torch.stack(act_ensemble(list(chunks), 0.01)))

    # DAgger: the expert's per-step labels along the learner's trajectory are its chunk targets.
    aggregated = demonstrations.with_episodes([demonstration_frames(rollout, demonstrations.specs)])
    played = torch.arange(len(demonstrations.goal), len(aggregated.goal))
    actions, mask = aggregated.action_chunks(played, k)
    expert = rollout.get(EXPERT_ACTION)
    torch.testing.assert_close(actions[0], expert[:k])
    assert mask[: steps - k + 1].all() and mask[-1].tolist() == [True, False, False, False]


def test_in_a_batch_of_two_envs_a_reset_clears_the_past_chunks_of_that_env_only(demonstrations):
    policy = make_policy(demonstrations, action_chunk=3).eval()
    env = TransformedEnv(
        SerialEnv(2, lambda: MultimodalPushTorchEnv(image_size=IMAGE_SIZE)), Compose(*policy.transforms())
    )
    try:
        env.set_seed(0)
        with torch.no_grad():
            state = env.reset()
            for _ in range(3):
                state = step_mdp(env.step(policy(state)))
            assert state.get(PAST_CHUNKS_FILLED).tolist() == [[1, 1], [1, 1]]
            kept = state.get(PAST_CHUNKS)[0].clone()
            state.set("_reset", torch.tensor([[False], [True]]))
            state = env.reset(state)
            assert state.get("is_init").squeeze(-1).tolist() == [False, True]
            assert state.get(PAST_CHUNKS_FILLED).tolist() == [[1, 1], [0, 0]]
            torch.testing.assert_close(state.get(PAST_CHUNKS)[0], kept)
            acted = policy(state)
            assert acted.get(("next", PAST_CHUNKS_FILLED)).tolist() == [[1, 1], [1, 0]]
            torch.testing.assert_close(acted.get("action")[1], acted.get(ACTION_CHUNK)[1, 0])
    finally:
        env.close()


def test_a_chunk_policy_round_trips_its_checkpoint_and_is_scored_on_its_first_action(
    demonstrations, tmp_path
):
    policy = make_policy(demonstrations, seed=2, action_chunk=3, chunk_decay=0.05).eval()
    assert BCConfig.from_dict(policy.config.to_dict()) == policy.config
    loaded = BCPolicy.from_checkpoint(policy.save(tmp_path / "policy"))
    assert loaded.config == policy.config and loaded.config.action_chunk == 3
    assert loaded.ensemble.decay == 0.05 and loaded.state_dict().keys() == policy.state_dict().keys()
    frames = demonstrations.split_frames["val"]
    batch = demonstrations.batch(frames)
    with torch.no_grad():
        chunk = loaded.predictor()(batch.exclude("action")).get(ACTION_CHUNK)
        torch.testing.assert_close(chunk, policy.predictor()(batch.exclude("action")).get(ACTION_CHUNK))
    assert chunk.shape == (len(frames), 3, demonstrations.action_dim)
    errors = validation_errors(loaded, demonstrations, "val", droppable=())
    first = ((chunk[:, 0] - batch.get("action")) ** 2).mean().item()
    assert errors["mse_all"] == pytest.approx(first, rel=1e-5)
    with pytest.raises(ValueError, match="action_chunk must be >= 1"):
        replace(policy.config, action_chunk=0)
