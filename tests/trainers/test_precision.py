"""The trainer's device path on CPU: prefetching, bf16 autocast, fp16 refusal, torch.compile."""

import shutil

import pytest
import torch
from tensordict import TensorDict

from mmf_rl import keys
from mmf_rl.datasets.prefetch import Prefetcher
from mmf_rl.trainers.trainer import Trainer, TrainerConfig, outputs_to_fp32
from tests.conftest import InMemoryLoader
from tests.trainers.test_trainer import build, combined_loss, small_forecaster, trainer_config


def weights(trainer: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in trainer.model.state_dict().items()}


def test_prefetching_trains_bit_identically_to_the_plain_loop(synthetic_task):
    # 7 steps over 5-batch epochs: the prefetch thread crosses an epoch while a step runs.
    runs = {}
    for prefetch in (False, True):
        model = small_forecaster()
        loader = InMemoryLoader(synthetic_task["train"][:160], batch_size=32)
        runs[prefetch] = Trainer(
            model, combined_loss(model), loader, trainer_config(total_steps=7, prefetch=prefetch)
        )
        runs[prefetch].train()
    plain, prefetched = runs[False], runs[True]
    assert (prefetched.epoch, prefetched.batch_in_epoch) == (plain.epoch, plain.batch_in_epoch) == (1, 2)
    for name, value in weights(plain).items():
        assert torch.equal(weights(prefetched)[name], value), name
    assert [h["train/loss"] for h in prefetched.history] == [h["train/loss"] for h in plain.history]


class LoaderMaking(InMemoryLoader):
    def __init__(self, *args, batch_making: str, **kwargs):
        super().__init__(*args, **kwargs)
        self.batch_making = batch_making


def batch_streams(synthetic_task, batch_making: str) -> dict:
    model = small_forecaster()
    loader = LoaderMaking(synthetic_task["train"][:64], batch_size=32, batch_making=batch_making)
    return {
        prefetch: Trainer(
            model, combined_loss(model), loader, trainer_config(prefetch=prefetch)
        )._batch_stream()
        for prefetch in ("auto", True, False)
    }


def test_prefetch_auto_makes_batches_on_the_steps_thread_on_cpu(synthetic_task):
    streams = batch_streams(synthetic_task, "thread_safe")
    assert TrainerConfig().prefetch == "auto"
    assert not isinstance(streams["auto"], Prefetcher) and not isinstance(streams[False], Prefetcher)
    assert isinstance(streams[True], Prefetcher) and streams[True]._thread is not None
    streams[True].close()
    with pytest.raises(ValueError, match="trainer.prefetch must be true, false or 'auto', found 'yes'"):
        TrainerConfig(prefetch="yes")


def test_batches_made_in_workers_are_prefetched_on_a_thread_unless_prefetch_is_false(synthetic_task):
    streams = batch_streams(synthetic_task, "in_workers")
    for prefetch in ("auto", True):
        assert isinstance(streams[prefetch], Prefetcher) and streams[prefetch]._thread is not None
        streams[prefetch].close()
    assert not isinstance(streams[False], Prefetcher)


def test_batches_drawing_from_the_global_rng_are_never_made_on_a_thread(synthetic_task):
    streams = batch_streams(synthetic_task, "global_rng")
    assert isinstance(streams[True], Prefetcher) and streams[True]._thread is None
    assert not isinstance(streams["auto"], Prefetcher) and not isinstance(streams[False], Prefetcher)
    with pytest.raises(ValueError, match=r"batch_making must be one of \['thread_safe', 'global_rng', "):
        batch_streams(synthetic_task, "in_threads")


def test_bf16_autocasts_the_forward_and_keeps_losses_and_weights_fp32(synthetic_task):
    model = small_forecaster()
    loader = InMemoryLoader(synthetic_task["train"][:96], batch_size=32)
    trainer = Trainer(model, combined_loss(model), loader, trainer_config(total_steps=3, precision="bf16"))
    forward_dtypes, loss_dtypes = set(), set()
    linear = next(m for m in trainer.model.modules() if isinstance(m, torch.nn.Linear))
    hook = linear.register_forward_hook(lambda m, a, out: forward_dtypes.add(out.dtype))
    step = trainer.loss_step.register_forward_hook(
        lambda m, a, out: loss_dtypes.update(v.dtype for k, v in out[1].items() if k.startswith("loss_"))
    )
    trainer.train()
    hook.remove(), step.remove()
    assert torch.bfloat16 in forward_dtypes and loss_dtypes == {torch.float32}
    assert all(p.dtype == torch.float32 and torch.isfinite(p).all() for p in trainer.model.parameters())
    # After training the model forecasts in fp32 again (evaluation, export).
    with torch.no_grad():
        out = trainer.model(synthetic_task["test"][:8].clone())
    assert out[keys.FORECAST_LOC].dtype == torch.float32


def test_without_the_cast_the_losses_would_see_bf16_forecasts(synthetic_task):
    model = small_forecaster()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        raw = model(synthetic_task["train"][:32].clone())
        handle = model.register_forward_hook(outputs_to_fp32)
        cast = model(synthetic_task["train"][:32].clone())
    handle.remove()
    assert raw[keys.FORECAST_LOC].dtype == torch.bfloat16
    assert cast[keys.FORECAST_LOC].dtype == cast[keys.FORECAST_SCALE].dtype == torch.float32
    assert cast[keys.present_key("pos")].dtype == torch.bool  # only low-precision floats change


def test_fp16_on_cpu_is_refused_naming_the_fix(synthetic_task, tmp_path):
    with pytest.raises(
        ValueError, match=r"trainer.precision=fp16 needs a CUDA device.*use trainer.precision=bf16"
    ):
        build(synthetic_task, tmp_path, precision="fp16")
    with pytest.raises(
        ValueError, match=r"trainer.precision must be one of \['fp32', 'bf16', 'fp16'\], found 'fp8'"
    ):
        TrainerConfig(precision="fp8")


class TinyRegression(torch.nn.Module):
    """A two-layer regression and its loss: what the compile test can afford to compile on a CPU."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.model = torch.nn.Sequential(torch.nn.Linear(4, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1))

    def forward(self, batch: TensorDict) -> TensorDict:
        return TensorDict({"loss_mse": ((self.model(batch["x"]) - batch["y"]) ** 2).mean()})


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("c++") is None and shutil.which("g++") is None,
    reason="torch.compile's inductor needs a C++ compiler",
)
@pytest.mark.timeout(300)
def test_compiled_training_step_trains_like_the_eager_one():
    g = torch.Generator().manual_seed(0)
    data = TensorDict({"x": torch.randn(32, 4, generator=g), "y": torch.randn(32, 1, generator=g)}, [32])
    runs = {}
    for compile_ in (False, True):
        loss = TinyRegression()
        trainer = Trainer(
            loss.model, loss, InMemoryLoader(data, 16), trainer_config(total_steps=2, compile=compile_)
        )
        trainer.train()
        runs[compile_] = weights(trainer)
    for name, value in runs[False].items():
        torch.testing.assert_close(runs[True][name], value, rtol=1e-5, atol=1e-6, msg=name)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="fp16 loss scaling runs on CUDA only")
def test_fp16_on_cuda_trains_with_a_grad_scaler_that_is_checkpointed(synthetic_task):
    model = small_forecaster().cuda()
    loader = InMemoryLoader(synthetic_task["train"][:320], batch_size=64)  # CPU batches, moved by the trainer
    trainer = Trainer(model, combined_loss(model), loader, trainer_config(total_steps=6, precision="fp16"))
    trainer.train()
    assert trainer.step == 6 and "grad_scaler" in trainer.state_dict()
    assert all(torch.isfinite(p).all() for p in model.parameters())
