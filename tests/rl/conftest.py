"""Fixtures of the RL glue tests."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.models.loading import load_trained_model
from mmf_rl.rl import Demonstrations, ForecastTable

RECORDED_ENVS = 3
BC_DROPPABLE = ("image", "force")  # the sensors the BC tests' policies may lose


@pytest.fixture(scope="module")
def recorded_steps(recorded_push_root) -> list[TensorDict]:
    """The first recorded push episodes as the steps of a batch of envs (one episode each): what
    the env emits, camera frames decoded from the recording's video."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from mmf_rl.record import CAMERA_KEY, CAMERA_VALID_KEY, FORCE_KEY, STATE_KEY, RecordConfig

    dataset = LeRobotDataset(RecordConfig.repo_id, root=recorded_push_root)
    episodes = [dataset.meta.episodes[e] for e in range(RECORDED_ENVS)]
    length = min(e["dataset_to_index"] - e["dataset_from_index"] for e in episodes)
    frames = [[dataset[e["dataset_from_index"] + t] for e in episodes] for t in range(length)]
    return [
        TensorDict(
            {
                keys.obs_key("image"): torch.stack(
                    [(f[CAMERA_KEY] * 255).round().to(torch.uint8) for f in step]
                ),
                keys.obs_key("force"): torch.stack([f[FORCE_KEY] for f in step]),
                keys.obs_key("proprio"): torch.stack([f[STATE_KEY] for f in step]),
                keys.present_key("image"): torch.stack([f[CAMERA_VALID_KEY].reshape(()) for f in step]),
                keys.present_key("force"): torch.ones(RECORDED_ENVS, dtype=torch.bool),
                keys.present_key("proprio"): torch.ones(RECORDED_ENVS, dtype=torch.bool),
            },
            batch_size=[RECORDED_ENVS],
        )
        for step in frames
    ]


@pytest.fixture(scope="module")
def forecaster(push_forecaster_run):
    """The session's tiny forecaster, loaded (once per module: a test may change the model it holds)."""
    return load_trained_model(push_forecaster_run / "checkpoints")


@pytest.fixture(scope="module")
def demonstrations(forecaster) -> Demonstrations:
    _, _, data_config = forecaster
    return Demonstrations(WindowDataset(DataConfig.from_dict(data_config)))


@pytest.fixture(scope="module")
def forecasts(demonstrations, forecaster) -> ForecastTable:
    model, stats, _ = forecaster
    return ForecastTable.compute(demonstrations, model, stats, BC_DROPPABLE, splits=("train", "val", "test"))
