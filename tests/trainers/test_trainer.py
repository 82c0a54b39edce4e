import functools
import itertools
import multiprocessing
from datetime import timedelta

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torchrl.record.loggers import CSVLogger

from mmf_rl import keys
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.configuration import compose_config, to_container
from mmf_rl.datasets import AugmentConfig, TrainingAugmentation, WindowDataset
from mmf_rl.eval.metrics import evaluate_forecasts
from mmf_rl.models import ForecasterConfig, MultimodalForecaster, build_loss, build_model
from mmf_rl.objectives import CombinedLoss, ELBOLoss, LossConfig, MissingModalityLoss
from mmf_rl.trainers.trainer import (
    Trainer,
    TrainerConfig,
    TrainingStopped,
    make_optimizer,
    make_scheduler,
    rng_state,
    seed_everything,
    set_rng_state,
)
from tests.conftest import SMALL_MODEL_SIZES, SYNTH_MODALITIES, InMemoryLoader, synthetic_motion_task
from tests.reliability.conftest import push_data_config


class Interrupt(Exception):
    pass


def train_until_interrupted(trainer: Trainer, step: int) -> None:
    """Train until ``step``, then stop as a killed run would (after that step, not at a checkpoint)."""

    def interrupt(t):
        if t.step == step:
            raise Interrupt

    trainer.register_op("post_steps", interrupt)
    with pytest.raises(Interrupt):
        trainer.train()


def small_forecaster() -> MultimodalForecaster:
    seed_everything(0)
    config = ForecasterConfig(
        modalities=SYNTH_MODALITIES,
        history=8,
        horizon=8,
        target_dim=2,
        d_model=16,
        d_latent=4,
        num_heads=2,
        mlp_hidden=32,
        head_hidden=32,
    )
    return MultimodalForecaster(config)


def combined_loss(model):
    return CombinedLoss(ELBOLoss(model, kl_warmup_steps=10), MissingModalityLoss(model))


def trainer_config(**overrides) -> TrainerConfig:
    return TrainerConfig(
        **{
            "total_steps": 12,
            "lr": 3e-3,
            "warmup_steps": 3,
            "log_every": 2,
            "eval_every": 6,
            "checkpoint_every": 6,
            "progress_bar": False,
            **overrides,
        }
    )


def build(synthetic_task, tmp_path, **overrides):
    model = small_forecaster()
    loss = combined_loss(model)
    config = trainer_config(**overrides)
    loader = InMemoryLoader(synthetic_task["train"][:320], batch_size=64, seed=0)  # 5 batches per epoch

    def evaluate(m):
        out = m(synthetic_task["test"][:256].clone())
        return {"val/mse": float(((out[keys.FORECAST_LOC] - out[keys.TARGET]) ** 2).mean())}

    return Trainer(
        model,
        loss,
        loader,
        config,
        run_dir=tmp_path,
        evaluate=evaluate,
        checkpoint_meta={"config": model.config.to_dict()},
    )


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

    train_until_interrupted(interrupted, 8)  # checkpoint at 6, two more steps are lost

    resumed = build(synthetic_task, tmp_path / "b")
    torch.manual_seed(1234)  # whatever the process did before: the checkpoint's RNG state wins
    resumed.resume(tmp_path / "b" / "checkpoints")
    assert resumed.step == 6 and resumed.epoch == 1 and resumed.batch_in_epoch == 1
    resumed.train()
    for (name, a), b in zip(
        reference.model.state_dict().items(), resumed.model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    assert int(resumed.loss_module.losses[0].num_updates) == 12


@pytest.fixture(scope="module")
def push_windows(recorded_push_root, tmp_path_factory) -> WindowDataset:
    return WindowDataset(push_data_config(recorded_push_root, tmp_path_factory.mktemp("cache")))


@functools.cache
def lerobot_augment() -> dict:
    return to_container(compose_config("train", ["augment=lerobot"]).augment)


def augmented_run(data: WindowDataset, run_dir, seen_images: list, workers: int = 1) -> Trainer:
    """A trainer over ``data`` augmented in ``workers`` worker processes (0: on the training thread),
    recording the images of each step."""
    seed_everything(0)
    model = build_model({"name": "forecaster", **SMALL_MODEL_SIZES["forecaster"]}, data.specs, 4, 3, 2)
    augment = TrainingAugmentation(
        AugmentConfig.from_dict({**lerobot_augment(), "workers": workers}), data.specs, 0
    )
    loader = data.loader("train", 16, seed=0, augment=augment)
    # 4 batches per epoch: the run resumes inside epoch 1 and crosses into epoch 2.
    config = trainer_config(total_steps=10, checkpoint_every=5, eval_every=100)
    trainer = Trainer(model, build_loss("forecaster", model, LossConfig()), loader, config, run_dir=run_dir)
    trainer.register_op(
        "batch_process", lambda batch: seen_images.append(batch.get(keys.obs_key("image")).clone()) or batch
    )
    return trainer


def test_a_resumed_run_replays_the_batches_augmented_in_a_worker(push_windows, tmp_path):
    # The uninterrupted run augments on the training thread: a worker process makes the same batches
    # (tests/datasets/test_augment.py), and its model the same draws.
    reference_images, images = [], []
    reference = augmented_run(push_windows, tmp_path / "a", reference_images, workers=0)
    assert len(reference.loader) == 4
    reference.train()

    interrupted = augmented_run(push_windows, tmp_path / "b", images)
    assert interrupted.prefetching  # "auto": a thread waits on the worker
    train_until_interrupted(interrupted, 7)  # checkpoint at 5, two more steps are lost
    assert not multiprocessing.active_children(), "the interrupted run left its worker running"
    assert all(torch.equal(a, b) for a, b in zip(images, reference_images[:7], strict=True))

    resumed_images = []
    resumed = augmented_run(push_windows, tmp_path / "b", resumed_images)
    resumed.resume(tmp_path / "b" / "checkpoints")
    assert (resumed.step, resumed.epoch, resumed.batch_in_epoch) == (5, 1, 1)
    resumed.train()
    assert not multiprocessing.active_children()
    assert len(resumed_images) == 5
    for step, (a, b) in enumerate(zip(resumed_images, reference_images[5:], strict=True), start=6):
        assert torch.equal(a, b), f"step {step} trained on other images than the uninterrupted run's"
    for (name, a), b in zip(
        reference.model.state_dict().items(), resumed.model.state_dict().values(), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)


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
    with pytest.raises(
        TrainingStopped, match=r"3 steps in a row had a non-finite loss.*step 1, epoch 0, batch 3"
    ):
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
    trainer = build(
        synthetic_task,
        tmp_path,
        total_steps=40,
        eval_every=2,
        early_stopping_patience=1,
        early_stopping_metric="val/constant",
    )
    trainer.evaluate = lambda m: {"val/constant": 1.0}
    trainer.train()
    assert trainer.step == 6  # best at 2, no improvement at 4 and 6 -> stop
    assert load_checkpoint(tmp_path / "checkpoints").step == 6


def test_early_stopping_on_a_metric_the_evaluation_lacks_is_an_error(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, early_stopping_patience=1, early_stopping_metric="val/loss")
    with pytest.raises(ValueError, match=r"early_stopping_metric='val/loss' is not among .*\['val/mse'\]"):
        trainer.train()


def test_default_early_stopping_metric_is_one_the_train_command_reports(synthetic_task, tmp_path):
    trainer = build(synthetic_task, tmp_path, total_steps=6, early_stopping_patience=3)
    # what `mmf-rl train` validates with (mmf_rl.trainers.training.make_trainer)
    trainer.evaluate = lambda m: {
        f"val/{k}": v for k, v in evaluate_forecasts(m, [synthetic_task["test"][:64]], lambda t: t).items()
    }
    metrics = trainer.train()
    assert trainer.best_metric == metrics[TrainerConfig().early_stopping_metric]


def test_bad_config_and_hook_names(synthetic_task, tmp_path):
    with pytest.raises(ValueError, match=r"unknown keys \['lr_schedul'\]"):
        TrainerConfig.from_dict({"lr_schedul": "cosine"})
    with pytest.raises(ValueError, match="lr_schedule must be 'constant' or 'cosine'"):
        TrainerConfig(lr_schedule="step")
    with pytest.raises(ValueError, match=r"trainer.grad_clip_norm must be >= 0, found -1.0"):
        TrainerConfig(grad_clip_norm=-1.0)
    with pytest.raises(ValueError, match=r"trainer.lr must be >= 0, found -0.001"):
        TrainerConfig(lr=-1e-3)
    with pytest.raises(ValueError, match="unknown hook point 'after_loss'"):
        build(synthetic_task, tmp_path).register_op("after_loss", print)


# --- data parallel: two gloo ranks against the definition, computed in one process ----------------

DP_STEPS = 8
DP_NAN_BATCH = 4  # rank 0's 4th batch holds a NaN: both ranks skip that step


def dp_loader(rank: int) -> InMemoryLoader:
    return InMemoryLoader(synthetic_motion_task(320, seed=10 + rank), batch_size=32, seed=rank)  # 10 batches


def dp_batch(batch, number: int, rank: int):
    """Rank 1 never sees "force" (an encoder unused on one rank); no rank sees "pos" in every third
    batch (unused on all ranks, after steps that left it Adam momentum); one NaN on rank 0 only."""
    batch = batch.clone()
    if rank == 1:
        batch[keys.present_key("force")] = torch.zeros(batch.shape[0], dtype=torch.bool)
    if number % 3 == 0:
        batch[keys.present_key("pos")] = torch.zeros(batch.shape[0], dtype=torch.bool)
    if rank == 0 and number == DP_NAN_BATCH:
        batch[keys.TARGET][0, 0, 0] = float(
            "nan"
        )  # a NaN input is refused by the model; a NaN target gives a NaN loss
    return batch


def train_rank(rank: int, store: str, out: str) -> None:
    torch.set_num_threads(1)
    # A bounded timeout: a rank left waiting in a collective fails the test instead of hanging it.
    dist.init_process_group(
        "gloo", init_method=f"file://{store}", rank=rank, world_size=2, timeout=timedelta(seconds=120)
    )
    try:
        model = small_forecaster()
        trainer = Trainer(
            model,
            combined_loss(model),
            dp_loader(rank),
            trainer_config(total_steps=DP_STEPS),
            rank=rank,
            world_size=2,
        )
        seed_everything(1 + rank)  # each rank draws its own latents and dropped modalities
        numbers = itertools.count(1)
        trainer.register_op("batch_process", lambda batch: dp_batch(batch, next(numbers), rank))
        trainer.train()
        result = {
            "weights": {k: v.clone() for k, v in model.state_dict().items()},
            "nonfinite_total": trainer.nonfinite_total,
            "pos_grads": [p.grad for p in model.encoders["pos"].parameters()],
        }
        # A loss that explodes on rank 1 only stops both ranks.
        trainer.config.total_steps += 2
        if rank == 1:
            trainer.register_op("batch_process", lambda b: b.set(keys.TARGET, b[keys.TARGET] * 1e6))
        try:
            trainer.train()
        except TrainingStopped as err:
            result["stopped"] = str(err)
        torch.save(result, f"{out}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


def data_parallel_by_definition() -> dict[str, torch.Tensor]:
    """Each rank's loss on its own batch and RNG stream; their gradients averaged (a rank without one
    adds zero; a parameter no rank used keeps no gradient, as in one process); clip; AdamW."""
    model = small_forecaster()
    losses = [combined_loss(model) for _ in range(2)]  # one KL warm-up counter per rank
    config = trainer_config(total_steps=DP_STEPS)
    optimizer = make_optimizer(model.parameters(), config)
    scheduler = make_scheduler(optimizer, config)
    params = list(model.parameters())
    rngs = []
    for rank in range(2):
        seed_everything(1 + rank)
        rngs.append(rng_state())
    streams = [iter(dp_loader(rank)) for rank in range(2)]  # one epoch covers DP_STEPS + 1 batches
    steps = 0
    for number in itertools.count(1):
        totals = []
        for rank in range(2):
            set_rng_state(rngs[rank])
            out = losses[rank](dp_batch(next(streams[rank]), number, rank))
            totals.append(sum(v for k, v in out.items() if k.startswith("loss_")))
            rngs[rank] = rng_state()
        if not all(torch.isfinite(t) for t in totals):
            continue
        grads = [torch.autograd.grad(t, params, allow_unused=True) for t in totals]
        for p, per_rank in zip(params, zip(*grads, strict=True), strict=True):
            present = [g for g in per_rank if g is not None]
            p.grad = sum(present) / 2 if present else None
        torch.nn.utils.clip_grad_norm_(params, config.grad_clip_norm)
        optimizer.step()
        scheduler.step()
        steps += 1
        if steps == DP_STEPS:
            return model.state_dict()


@pytest.mark.slow
def test_two_gloo_ranks_average_gradients_skip_and_stop_together(tmp_path):
    mp.spawn(train_rank, args=(str(tmp_path / "store"), str(tmp_path)), nprocs=2)
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=True) for r in range(2)]
    for name, value in ranks[0]["weights"].items():
        assert torch.equal(value, ranks[1]["weights"][name]), name
    assert [r["nonfinite_total"] for r in ranks] == [1, 1]
    # the last step's batches (number 9) had no "pos": its encoder got no gradient on any rank
    assert all(g is None for r in ranks for g in r["pos_grads"])
    assert "loss exploded" in ranks[0]["stopped"] and ranks[0]["stopped"] == ranks[1]["stopped"]
    threads = torch.get_num_threads()
    # The ranks' kernels: Adam turns rounding noise in near-zero gradients into whole steps.
    torch.set_num_threads(1)
    try:
        expected = data_parallel_by_definition()
    finally:
        torch.set_num_threads(threads)
    for name, value in expected.items():
        torch.testing.assert_close(ranks[0]["weights"][name], value, msg=name)


@pytest.mark.parametrize("fused", [True, False])
def test_the_optimizer_is_adamw_fused_or_its_per_parameter_loop(fused):
    model = small_forecaster()
    optimizer = make_optimizer(model.parameters(), trainer_config(fused_optimizer=fused))
    group = optimizer.param_groups[0]
    assert isinstance(optimizer, torch.optim.AdamW)
    assert bool(group["fused"]) is fused and group["foreach"] in (False, None)
    before = [p.detach().clone() for p in model.parameters()]
    sum(p.sum() for p in model.parameters()).backward()
    optimizer.step()
    assert all(not torch.equal(b, p) for b, p in zip(before, model.parameters(), strict=True))
