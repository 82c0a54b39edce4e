import pytest
import torch
from torchrl.record.loggers import CSVLogger

from mmf_rl import keys
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import CombinedLoss, ELBOLoss, MissingModalityLoss
from mmf_rl.trainers import load_checkpoint
from mmf_rl.trainers.trainer import Trainer, TrainerConfig, TrainingStopped, seed_everything
from tests.conftest import SYNTH_MODALITIES, InMemoryLoader


class Interrupt(Exception):
    pass


def build(synthetic_task, tmp_path, **overrides):
    seed_everything(0)
    model = MultimodalForecaster(ForecasterConfig(modalities=SYNTH_MODALITIES, history=8, horizon=8, target_dim=2,
                                                  d_model=16, d_latent=4, num_heads=2, mlp_hidden=32, head_hidden=32))
    loss = CombinedLoss(ELBOLoss(model, kl_warmup_steps=10), MissingModalityLoss(model))
    config = TrainerConfig(**{"total_steps": 12, "lr": 3e-3, "warmup_steps": 3, "log_every": 2, "eval_every": 6,
                              "checkpoint_every": 6, "progress_bar": False, **overrides})
    loader = InMemoryLoader(synthetic_task["train"][:320], batch_size=64, seed=0)  # 5 batches per epoch

    def evaluate(m):
        out = m(synthetic_task["test"][:256].clone())
        return {"val/mse": float(((out[keys.FORECAST_LOC] - out[keys.TARGET]) ** 2).mean())}

    return Trainer(model, loss, loader, config, run_dir=tmp_path, evaluate=evaluate,
                   checkpoint_meta={"config": model.config.to_dict()})


def test_trains_logs_evaluates_and_checkpoints(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, total_steps=30, eval_every=10, checkpoint_every=10)
    trainer.logger = CSVLogger("run", log_dir=str(tmp_path / "logs"))
    metrics = trainer.train()
    assert trainer.step == 30 and trainer.state_dict()["epoch"] == 6  # 5 batches per epoch
    assert trainer.history[-1]["train/loss"] < trainer.history[0]["train/loss"]
    assert "val/mse" in metrics
    assert load_checkpoint(tmp_path / "checkpoints").step == 30
    lines = (tmp_path / "logs" / "run" / "scalars" / "train" / "loss.csv").read_text().splitlines()
    assert len(lines) == 15 and lines[-1].startswith("30,")
    assert (tmp_path / "logs" / "run" / "scalars" / "val" / "mse.csv").exists()


def test_resume_after_interrupt_equals_uninterrupted_run(synthetic_task, tmp_path):
    reference = build(synthetic_task, tmp_path / "a")
    reference.train()

    interrupted = build(synthetic_task, tmp_path / "b")

    def die_after_checkpoint(trainer):
        if trainer.step == 8:  # checkpoint at 6, two more steps are lost
            raise Interrupt

    interrupted.register_op("post_steps", die_after_checkpoint)
    with pytest.raises(Interrupt):
        interrupted.train()

    resumed = build(synthetic_task, tmp_path / "b")
    torch.manual_seed(1234)  # whatever the process did before: the checkpoint's RNG state wins
    resumed.resume(tmp_path / "b" / "checkpoints")
    assert resumed.step == 6 and resumed.epoch == 1 and resumed.batch_in_epoch == 1
    resumed.train()
    for (name, a), b in zip(reference.model.state_dict().items(), resumed.model.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    assert int(resumed.loss_module.losses[0].num_updates) == 12


def poison(step_numbers):
    calls = {"n": 0}

    def op(batch):
        calls["n"] += 1
        if calls["n"] in step_numbers:
            batch = batch.clone()
            batch[keys.TARGET][0, 0, 0] = float("nan")  # a NaN input would be refused by the model
        return batch

    return op


def test_nonfinite_batch_is_skipped_and_counted(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path)
    trainer.register_op("batch_process", poison({3}))
    trainer.train()
    assert trainer.step == 12 and trainer.nonfinite_total == 1
    assert all(torch.isfinite(p).all() for p in trainer.model.parameters())


def test_repeated_nonfinite_batches_stop_with_a_message_naming_the_batch(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, max_nonfinite_steps=2)
    trainer.register_op("batch_process", poison({2, 3, 4}))
    with pytest.raises(TrainingStopped, match=r"3 steps in a row had a non-finite loss.*step 1, epoch 0, batch 3"):
        trainer.train()


def test_exploding_loss_stops_and_names_last_good_checkpoint(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, checkpoint_every=2)

    def explode(batch):
        if trainer.step == 5:
            batch = batch.clone()
            batch[keys.TARGET] = batch[keys.TARGET] * 1e6
        return batch

    trainer.register_op("batch_process", explode)
    with pytest.raises(TrainingStopped, match=r"loss exploded to .* at step 5 .*step_000000004"):
        trainer.train()


def test_early_stopping(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, total_steps=40, eval_every=2, early_stopping_patience=1,
                    early_stopping_metric="val/constant")
    trainer.evaluate = lambda m: {"val/constant": 1.0}
    trainer.train()
    assert trainer.step == 6  # best at 2, no improvement at 4 and 6 -> stop
    assert load_checkpoint(tmp_path / "checkpoints").step == 6


def test_bad_config_and_hook_names(synthetic_task, tmp_path):
    with pytest.raises(ValueError, match=r"unknown keys \['lr_schedul'\]"):
        TrainerConfig.from_dict({"lr_schedul": "cosine"})
    with pytest.raises(ValueError, match="lr_schedule must be 'constant' or 'cosine'"):
        TrainerConfig(lr_schedule="step")
    with pytest.raises(ValueError, match="unknown hook point 'after_loss'"):
        build(synthetic_task, tmp_path).register_op("after_loss", print)
