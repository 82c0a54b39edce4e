"""`mmf-rl train model.learned_samples=K sampler.steps=N` on the project's own push recording: the sampler
trains after the forecaster, on the frozen forecaster, into the run's last checkpoint and exported model."""

import logging

import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import list_checkpoints, load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.models import MultimodalForecaster, load_trained_model
from mmf_rl.trainers.latent_sampler import SamplerConfig
from tests.conftest import push_train_overrides

SAMPLER = ["model.learned_samples=4", "sampler.steps=8", "sampler.batch_size=8"]


@pytest.fixture(scope="module")
def runs(push_forecaster_run, recorded_push_root, push_cache_dir, tmp_path_factory):
    """The same tiny run without a learned sampler (the session's, `push_train_overrides`) and with one."""
    sampler = tmp_path_factory.mktemp("sampler_runs") / "sampler"
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, sampler)
    assert cli(["train", *overrides, *SAMPLER]) == 0
    return {"plain": push_forecaster_run, "sampler": sampler}


def test_the_forecaster_is_the_run_without_a_sampler_and_the_sampler_learned(runs):
    plain, _, _ = load_trained_model(runs["plain"] / "checkpoints", map_location="cpu")
    sampled, _, _ = load_trained_model(runs["sampler"] / "checkpoints", map_location="cpu")
    assert isinstance(sampled, MultimodalForecaster) and sampled.latent_sampler is not None
    state = sampled.state_dict()
    for name, value in plain.state_dict().items():
        assert torch.equal(state[name], value), name
    # The forecaster's training leaves the sampler as built (no gradient reaches it); its phase moves it.
    first, last = (load_checkpoint(p).model_state for p in list_checkpoints(runs["sampler"] / "checkpoints"))
    sampler_keys = [k for k in last if k.startswith("latent_sampler.")]
    assert sampler_keys and all(not torch.equal(first[k], last[k]) for k in sampler_keys)
    meta = load_checkpoint(list_checkpoints(runs["sampler"] / "checkpoints")[-1]).meta
    assert meta["learned_sampler"]["steps"] == 8 and meta["calibration"] is not None


def test_the_exported_model_samples_the_learned_codes(runs):
    exported, _, _ = load_trained_model(runs["sampler"] / "model", map_location="cpu")
    data = WindowDataset(DataConfig.from_dict(exported.data_config))
    batch = next(iter(data.loader("test", 8)))
    with torch.no_grad():
        samples = exported.sample(batch.exclude(keys.TARGET), 4).get(keys.FORECAST_SAMPLES)
        learned = exported.learned_samples(batch.exclude(keys.TARGET))[0]
    torch.testing.assert_close(samples, learned)
    assert samples.std(1).mean() > 0  # four different forecasts


def test_a_finished_run_resumed_keeps_its_trained_sampler(runs, recorded_push_root, push_cache_dir, caplog):
    path = list_checkpoints(runs["sampler"] / "checkpoints")[-1]
    before = load_checkpoint(path).model_state
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, runs["sampler"])
    with caplog.at_level(logging.INFO, logger="mmf_rl"):
        assert cli(["train", *overrides, *SAMPLER, "resume=true"]) == 0
    assert "learned sampler already trained" in caplog.text
    after = load_checkpoint(list_checkpoints(runs["sampler"] / "checkpoints")[-1]).model_state
    for name, value in before.items():
        assert torch.equal(after[name], value), name


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["model.learned_samples=4"], "sampler.steps=0 leaves untrained; set sampler.steps"),
        (["sampler.steps=8"], "the model has none; set model.learned_samples=K"),
        (["model.learned_samples=4", "sampler.steps=8", "sampler.batch_size=0"], "sampler.batch_size must"),
    ],
)
def test_sampler_settings_that_cannot_work_are_refused_before_training(
    recorded_push_root, tmp_path, capsys, extra, message
):
    overrides = push_train_overrides(recorded_push_root, tmp_path / "cache", tmp_path / "run")
    assert cli(["train", *overrides, *extra]) == 1
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_unknown_sampler_settings_are_refused():
    with pytest.raises(ValueError, match="sampler config"):
        SamplerConfig.from_dict({"step": 10})
