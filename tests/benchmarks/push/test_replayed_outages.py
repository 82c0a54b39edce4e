"""Training outages replayed through the env's own outage processes, on the recorded push data."""

from __future__ import annotations

import json

import pytest
import torch

from benchmarks.push import replayed_outages
from benchmarks.push.closed_loop import sensor_outage
from benchmarks.push.replayed_outages import ReplayedOutages
from mmf_rl import keys
from mmf_rl.checkpoint import list_checkpoints
from mmf_rl.envs.torchrl_env import GOAL
from mmf_rl.rl import (
    BCPolicy,
    DemonstrationLoader,
    ForecastTable,
    ForecastTransform,
    HistoryWindow,
    train_bc,
)
from mmf_rl.rl.demonstrations import ACTION
from mmf_rl.rl.latched_forecast import LatchedForecastTable, LatchedForecastTransform
from mmf_rl.trainers.trainer import TrainerConfig
from tests.rl.test_bc import make_policy

NO_DROP, NO_IMAGE = 0, 1  # `drop_sets(("image", "force"))`: nothing, then the camera


def window_of(demonstrations) -> HistoryWindow:
    return HistoryWindow(demonstrations.specs, demonstrations.normalizer.stats, demonstrations.history)


def replay(demonstrations, outages, forecast=None, split="train") -> ReplayedOutages:
    return ReplayedOutages.replay(demonstrations, split, outages, window_of(demonstrations), forecast)


@pytest.fixture(scope="module")
def latched_replay(demonstrations, forecaster) -> ReplayedOutages:
    model, stats, data_config = forecaster
    latched = LatchedForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    return replay(
        demonstrations, [("all", None), ("camera dies", sensor_outage("image", "dies", seed=3))], latched
    )


def test_replays_without_the_camera_or_with_every_sensor_serve_the_forecast_tables_entries(
    demonstrations, forecasts, forecaster
):
    """The forecasts replayed through `ForecastTransform` are the `ForecastTable`'s, computed from
    windows built offline: with every sensor, and with the camera off for whole episodes."""
    model, stats, data_config = forecaster
    outages = [("all", None), ("camera off", sensor_outage("image", "episode", seed=0))]
    replayed = replay(
        demonstrations, outages, ForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    )
    frames = demonstrations.split_frames["train"]
    assert bool(replayed.replayed[frames].all()) and not bool(
        replayed.replayed[demonstrations.split_frames["val"]].any()
    )
    assert not replayed.absent["image"][0, frames].any() and replayed.absent["image"][1, frames].all()
    assert not replayed.absent["force"][:, frames].any() and replayed.droppable == ("image",)
    for index, drop in [(0, NO_DROP), (1, NO_IMAGE)]:
        torch.testing.assert_close(
            replayed.forecast[keys.FORECAST_LOC][index, frames], forecasts.loc[frames, drop]
        )
        torch.testing.assert_close(
            replayed.forecast[keys.FORECAST_SCALE][index, frames], forecasts.scale[frames, drop]
        )
    assert keys.FORECAST_AGE not in replayed.forecast  # a fresh forecast has no age


def test_episodes_of_other_lengths_over_passes_of_one_size_keep_nothing_of_the_replay_before(
    demonstrations, forecaster, monkeypatch
):
    """Episodes of 40, 40, 7 and 23 frames in passes of two (the second pass reuses the first's
    state, same batch), replayed with every sensor, then the camera off, then every sensor again
    through one latched transform: each replay serves the forecasts computed offline, frame by frame,
    so no window or latch leaks between episodes, passes or replays."""
    monkeypatch.setattr(replayed_outages, "EPISODES_PER_PASS", 2)
    added = []
    for start, length in [(0, 7), (demonstrations.split_frames["train"][0], 23)]:
        rows = torch.arange(int(start), int(start) + length)
        episode = demonstrations.env_observation(rows)
        episode.update({GOAL: demonstrations.goal[rows], ACTION: demonstrations.action[rows]})
        added.append(episode)
    longer = demonstrations.with_episodes(added)
    assert sorted(longer.episodes("train")[1].tolist()) == [7, 23, 40, 40]
    model, stats, data_config = forecaster
    table = ForecastTable.compute(longer, model, stats, ["image"], splits=("train",))
    latched = LatchedForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    off = ("camera off", sensor_outage("image", "episode", seed=0))
    replayed = replay(longer, [("all", None), off, ("all", None)], latched)
    frames = longer.split_frames["train"]
    for index, drop in [(0, NO_DROP), (1, NO_IMAGE), (2, NO_DROP)]:
        torch.testing.assert_close(
            replayed.forecast[keys.FORECAST_LOC][index, frames], table.loc[frames, drop]
        )
        assert not replayed.forecast[keys.FORECAST_AGE][index, frames].any(), "no latch served"
    assert replayed.absent["image"][1, frames].all() and not replayed.absent["image"][[0, 2]][:, frames].any()


def test_a_dying_camera_stays_dead_and_its_latch_ages_a_step_per_step(demonstrations, latched_replay):
    starts, lengths = demonstrations.episodes("train")
    image, age = latched_replay.absent["image"][1], latched_replay.forecast[keys.FORECAST_AGE][1]
    died = 0
    for start, length in zip(starts.tolist(), lengths.tolist(), strict=True):
        out, ages = image[start : start + length], age[start : start + length]
        assert not out[0], "the camera delivers at least its first reading"
        assert bool((out[1:] >= out[:-1]).all()), "once dead, it stays dead"
        assert bool((ages[~out] == 0).all())
        dead = out.nonzero().flatten()
        if len(dead):
            died += 1
            torch.testing.assert_close(ages[dead], torch.arange(1, len(dead) + 1, dtype=ages.dtype))
    assert died, "some camera died within its episode"
    assert not latched_replay.absent["image"][0].any()


def test_draws_are_seeded_and_give_each_sample_one_replay_whole(demonstrations, latched_replay):
    frames = demonstrations.split_frames["train"]

    def draw(seed):
        return latched_replay.draw(frames, torch.Generator().manual_seed(seed), with_forecasts=True)

    (absent, served), (again, _), (other, _) = draw(0), draw(0), draw(1)
    assert torch.equal(absent["image"], again["image"]) and not torch.equal(absent["image"], other["image"])
    assert 0 < absent["image"].float().mean() < 1
    loc = latched_replay.forecast[keys.FORECAST_LOC]
    age = latched_replay.forecast[keys.FORECAST_AGE]
    for i, frame in enumerate(frames.tolist()):
        replays = [
            r
            for r in range(len(latched_replay.labels))
            if bool(latched_replay.absent["image"][r, frame] == absent["image"][i])
            and torch.equal(loc[r, frame], served[keys.FORECAST_LOC][i])
            and bool(age[r, frame] == served[keys.FORECAST_AGE][i])
        ]
        assert replays, f"sample {i}: its absences and forecast come from one replay"
    assert latched_replay.draw(frames, torch.Generator(), with_forecasts=False)[1] == {}
    with pytest.raises(ValueError, match="were not replayed; replay the split"):
        latched_replay.draw(demonstrations.split_frames["val"], torch.Generator(), with_forecasts=False)


def test_a_latched_policy_trains_on_replayed_outages_and_records_them(
    demonstrations, forecasts, forecaster, latched_replay, tmp_path
):
    table = LatchedForecastTable.for_trained(forecasts, demonstrations, *forecaster)
    policy = make_policy(demonstrations, table)
    config = TrainerConfig(total_steps=4, batch_size=16, eval_every=4, checkpoint_every=4, progress_bar=False)
    metrics = train_bc(
        policy, demonstrations, config, dropout={}, forecasts=table, outages=latched_replay, run_dir=tmp_path
    )
    assert {"val/mse_all", "val/mse_no_image"} <= set(metrics) and "val/mse_no_force" not in metrics
    meta = json.loads((list_checkpoints(tmp_path / "checkpoints")[-1] / "meta.json").read_text())
    assert meta["replayed_outages"] == ["all", "camera dies"] and meta["dropout"] == {}
    assert BCPolicy.from_checkpoint(tmp_path / "checkpoints").config == policy.config


def test_train_bc_refuses_replays_of_what_the_policy_does_not_read(
    demonstrations, forecasts, forecaster, latched_replay
):
    """Outages replayed through another window or forecast than the policy's, or given with a dropout,
    stop the training before it starts, naming the fix."""
    model, stats, data_config = forecaster
    table = LatchedForecastTable.for_trained(forecasts, demonstrations, *forecaster)
    config = TrainerConfig(total_steps=4, batch_size=16, eval_every=4, checkpoint_every=4, progress_bar=False)
    fresh = ForecastTransform.for_trained(model, stats, data_config, denormalize=False)
    normalizer = demonstrations.normalizer
    longer = HistoryWindow(demonstrations.specs, normalizer.stats, demonstrations.history + 1)
    longer_window = ReplayedOutages.replay(demonstrations, "train", [("all", None)], longer)
    camera_only = ForecastTable.compute(demonstrations, model, stats, ["image"], splits=("train", "val"))
    force_off = replay(demonstrations, [("force off", sensor_outage("force", "episode", seed=0))], fresh)
    refused = [
        (camera_only, force_off, {}, "training removes \\['force'\\].*with droppable=\\['force'\\]"),
        (table, latched_replay, {"image": 0.3}, "replace the dropout.*pass dropout=\\{\\}"),
        (table, replay(demonstrations, [("all", None)]), {}, "served no forecast; replay them with"),
        (table, replay(demonstrations, [("all", None)], fresh), {}, "latch rule None; replay them with"),
        (
            None,
            longer_window,
            {},
            f"window of {demonstrations.history + 1} steps.*reads {demonstrations.history},.*history_window",
        ),
    ]
    for read, outages, dropout, message in refused:
        with pytest.raises(ValueError, match=message):
            train_bc(
                make_policy(demonstrations, read),
                demonstrations,
                config,
                dropout=dropout,
                forecasts=read,
                outages=outages,
            )


def test_a_replay_refuses_a_split_without_frames_and_forecasts_in_target_units(demonstrations, forecaster):
    with pytest.raises(ValueError, match="the 'tain' split has no demonstration frame"):
        replay(demonstrations, [("all", None)], split="tain")
    units = ForecastTransform.for_trained(*forecaster, denormalize=True)
    with pytest.raises(ValueError, match="denormalize=False"):
        replay(demonstrations, [("all", None)], units)


def test_a_loader_takes_replayed_outages_or_dropout_not_both(demonstrations, latched_replay):
    with pytest.raises(ValueError, match="replace dropout and absent"):
        DemonstrationLoader(demonstrations, "train", 8, dropout={"image": 0.3}, outages=latched_replay)
    batch = next(iter(DemonstrationLoader(demonstrations, "train", 64, outages=latched_replay)))
    assert keys.FORECAST_LOC not in batch.keys(True), "a policy without forecasts gets none"
    present = batch.get((keys.HISTORY, *keys.present_key("image")))
    assert 0 < present.float().mean() < 1


def test_the_absent_fraction_of_a_process_counts_each_of_its_replays():
    """A process replayed with two seeds (two replays of one label) reports both draws, not the last."""
    image = torch.tensor([[True, True, False], [False, False, False], [True, False, False]])
    replayed = ReplayedOutages(
        labels=["camera bursts", "all", "camera bursts"],
        replayed=torch.tensor([True, True, False]),
        absent={"image": image},
        forecast={},
        history=4,
        stride=1,
        rule=None,
    )
    assert replayed.absent_fraction() == {"camera bursts": {"image": 0.75}, "all": {"image": 0.0}}
