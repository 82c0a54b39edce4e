"""Fine-tuning (`init_from`): weights from a trained run, new optimizer, step 0; mismatches named."""

import re

import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.models import load_trained_model
from tests.conftest import push_train_overrides


def test_fine_tuning_starts_from_the_weights_at_step_zero(
    push_forecaster_run, push_cache_dir, recorded_push_root, tmp_path, capsys
):
    source = load_checkpoint(push_forecaster_run / "checkpoints")
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, tmp_path / "tuned", steps=3)
    # lr = 0: the weights after fine-tuning are the ones it started from
    assert cli(["train", *overrides, f"init_from={push_forecaster_run}", "trainer.lr=0.0"]) == 0
    assert "fine-tuning from" in capsys.readouterr().err
    tuned = load_checkpoint(tmp_path / "tuned" / "checkpoints")
    assert tuned.step == 3, "a fine-tuning run counts its own steps from 0"
    assert tuned.trainer_state["scheduler"]["last_epoch"] == 3
    assert all(torch.equal(tuned.model_state[k], v) for k, v in source.model_state.items())

    # the run's final model, as save_pretrained wrote it, is a source too, and forecasts like the checkpoint
    assert (
        cli(
            [
                "train",
                *overrides,
                f"run_dir={tmp_path / 'again'}",
                f"init_from={push_forecaster_run / 'model'}",
                "trainer.lr=0.0",
            ]
        )
        == 0
    )
    again = load_checkpoint(tmp_path / "again" / "checkpoints")
    assert all(torch.equal(again.model_state[k], v) for k, v in source.model_state.items())
    exported, stats, data = load_trained_model(push_forecaster_run / "model")
    checkpointed, _, data_from_checkpoint = load_trained_model(push_forecaster_run)
    assert data["image_size"] == data_from_checkpoint["image_size"] == [32, 32]
    assert torch.equal(stats["target/std"], source.tensors["target/std"])
    batch = next(iter(WindowDataset(DataConfig.from_dict(data)).loader("val", 8)))
    forecasts = [m(batch.clone()).get(keys.FORECAST_LOC) for m in (exported, checkpointed)]
    assert torch.equal(*forecasts)


def test_a_sampler_is_never_copied_and_a_run_may_add_one(
    push_forecaster_run, push_cache_dir, recorded_push_root, tmp_path
):
    """A run with a learned sampler starts from a source without one (its forecaster copied, its sampler
    trained anew), and a run without one starts from that run: only the forecaster's weights travel."""
    source = load_checkpoint(push_forecaster_run / "checkpoints")
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, tmp_path / "with", steps=3)
    sampler = ["model.learned_samples=4", "sampler.steps=4", "sampler.batch_size=8"]
    assert cli(["train", *overrides, *sampler, f"init_from={push_forecaster_run}", "trainer.lr=0.0"]) == 0
    with_sampler = load_checkpoint(tmp_path / "with" / "checkpoints")
    assert with_sampler.meta["learned_sampler"]["steps"] == 4
    sampler_keys = {k for k in with_sampler.model_state if k.startswith("latent_sampler.")}
    assert sampler_keys and sampler_keys.isdisjoint(source.model_state)
    assert all(torch.equal(with_sampler.model_state[k], v) for k, v in source.model_state.items())

    back = [*overrides, f"run_dir={tmp_path / 'without'}", f"init_from={tmp_path / 'with'}", "trainer.lr=0.0"]
    assert cli(["train", *back]) == 0
    without = load_checkpoint(tmp_path / "without" / "checkpoints")
    assert set(without.model_state) == set(source.model_state)
    assert all(torch.equal(without.model_state[k], v) for k, v in source.model_state.items())


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["model.d_latent=6"],
            r"posterior_head.2.bias: expected \[12\], found \[8\].*model.d_latent: this run 6, source 4",
        ),
        (
            ["data.image_size=[16,16]"],
            r"modality 'image': this run has \('image', \(3, 16, 16\)\), .* has \('image', \(3, 32, 32\)\)",
        ),
        (["~data.modalities.force"], r"modality 'force': this run has none, .* has \('sequence', \(6,\)\)"),
        (["model=lf_lstm"], r"holds a 'forecaster' model, but this run builds 'lf_lstm'"),
    ],
)
def test_mismatches_are_named(
    push_forecaster_run, push_cache_dir, recorded_push_root, tmp_path, capsys, args, message
):
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, tmp_path / "tuned", steps=2)
    if args == ["model=lf_lstm"]:
        overrides = [
            o for o in overrides if not o.startswith(("model.d_latent", "model.num_heads", "model.mlp"))
        ]
    assert cli(["train", *overrides, *args, f"init_from={push_forecaster_run}"]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]  # after any cache-building progress bar
    assert err.startswith("mmf-rl train: error:") and re.search(message, err), err


def test_init_from_a_missing_run_is_a_one_line_error(recorded_push_root, push_cache_dir, tmp_path, capsys):
    overrides = push_train_overrides(recorded_push_root, push_cache_dir, tmp_path / "tuned", steps=2)
    assert cli(["train", *overrides, f"init_from={tmp_path / 'nowhere'}"]) == 1
    assert "does not exist" in capsys.readouterr().err
