"""``decode_from="constant_velocity"``: the forecaster's decoded means are offsets from the constant-velocity
extrapolation of ``"target_past"``, on windows of the real ETH/UCY files (a small cut of them)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
import yaml

from mmf_rl import keys
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.eval.metrics import baseline_metrics, point_errors
from mmf_rl.models import ForecasterConfig, MultimodalForecaster, build_model
from mmf_rl.models.baselines.constant_velocity import constant_velocity

IMAGE = 16  # the scene crops, resized small
SMALL = {"d_model": 16, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32, "head_hidden": 32}


@pytest.fixture(scope="module")
def eth(ethucy_cut, tmp_path_factory) -> tuple[Path, dict]:
    """The eth fold of the session's cut of the real ETH/UCY files: its data config file and dict (small
    scene crops, a window cache of its own)."""
    path = ethucy_cut[1] / "eth.yaml"
    config = yaml.safe_load(path.read_text()) | {
        "cache_dir": str(tmp_path_factory.mktemp("decode_from") / "cache"),
        "image_size": [IMAGE, IMAGE],
    }
    return path, config


@pytest.fixture(scope="module")
def data(eth):
    from mmf_rl.datasets import DataConfig, WindowDataset

    return WindowDataset(DataConfig.from_dict(eth[1]))


@pytest.fixture(scope="module")
def windows(data):
    """A batch of the fold's val windows (with ``"target_past"``: ETH/UCY's configs include it)."""
    batch = data.batch(data.split_windows["val"][:16])
    assert keys.TARGET_PAST in batch.keys()
    return batch


def forecaster(data, **settings) -> MultimodalForecaster:
    torch.manual_seed(0)
    specs = data.specs
    model = build_model(
        {"name": "forecaster", **SMALL, **settings}, specs, data.config.history, data.config.horizon, 2
    )
    return model.eval()


def zero_decoder(model: MultimodalForecaster) -> MultimodalForecaster:
    """The decoder's last layer zeroed: every decoded loc is 0 (the offset from the origin)."""
    last = [m for m in model.decoder.head.modules() if isinstance(m, torch.nn.Linear)][-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    return model


def test_a_zero_decoder_forecasts_constant_velocity_in_metres_as_eval_scores_it(data, windows):
    model = zero_decoder(forecaster(data, decode_from="constant_velocity"))
    with torch.no_grad():
        loc = model(windows.clone())[keys.FORECAST_LOC]
    denormalize = data.normalizer.denormalize_target
    # The extrapolation in metres of the past in metres: the normalised frame's extrapolation denormalised
    # (the normaliser subtracts a mean, which an extrapolation's weights, summing to 1, carry through).
    in_metres = constant_velocity(denormalize(windows[keys.TARGET_PAST]), loc.shape[1])
    torch.testing.assert_close(denormalize(loc), in_metres, atol=1e-4, rtol=1e-5)
    assert data.normalizer.stats["target/mean"].abs().max() > 1e-3  # a mean is subtracted indeed
    # The model's point errors are eval's constant-velocity reference's.
    reference = baseline_metrics(windows, denormalize)
    target = windows[keys.TARGET]
    errors = point_errors(loc, target, denormalize(loc), denormalize(target))
    for name in ("ade", "fde", "mse"):
        torch.testing.assert_close(errors[name], reference[f"cv_{name}"], atol=1e-5, rtol=1e-4)


def same_weights(data, **settings) -> tuple[MultimodalForecaster, MultimodalForecaster]:
    """The model with ``settings`` decoding from zero and from constant velocity, same weights."""
    plain = forecaster(data, **settings)
    shifted = forecaster(data, decode_from="constant_velocity", **settings)
    shifted.load_state_dict(plain.state_dict())
    return plain, shifted


def origin_of(model, windows) -> torch.Tensor:
    return constant_velocity(windows[keys.TARGET_PAST], model.config.horizon)


@pytest.mark.parametrize("settings", [{}, {"prior": "learned", "eval_latent": "predictive"}])
def test_the_forecast_and_prior_samples_shift_by_the_extrapolation_the_scale_does_not(
    data, windows, settings
):
    plain, shifted = same_weights(data, **settings)
    cv = origin_of(shifted, windows)
    with torch.no_grad():
        a, b = plain(windows.clone()), shifted(windows.clone())
        torch.testing.assert_close(b[keys.FORECAST_LOC], a[keys.FORECAST_LOC] + cv)
        torch.testing.assert_close(b[keys.FORECAST_SCALE], a[keys.FORECAST_SCALE])
        torch.manual_seed(1)
        samples = plain.sample(windows.clone(), 5)[keys.FORECAST_SAMPLES]
        torch.manual_seed(1)
        moved = shifted.sample(windows.clone(), 5)[keys.FORECAST_SAMPLES]
    torch.testing.assert_close(moved, samples + cv[:, None])


def test_learned_sampler_samples_shift_alike(data, windows):
    plain, shifted = same_weights(data, learned_samples=3)
    with torch.no_grad():
        samples = plain.sample(windows.clone(), 3)[keys.FORECAST_SAMPLES]
        moved = shifted.sample(windows.clone(), 3)[keys.FORECAST_SAMPLES]
    torch.testing.assert_close(moved, samples + origin_of(shifted, windows)[:, None])


@pytest.mark.parametrize("posterior_reads", ["residual", "target"])
def test_training_decodes_shift_alike(data, windows, posterior_reads):
    """Train mode: the posterior decode, the L_mis student's, the GSNN and best-of-K prior decodes. The
    model decoding from zero reads the future its twin's posterior reads: the residual, or the target."""
    plain, shifted = same_weights(data, prior="learned", posterior_reads=posterior_reads)
    cv = origin_of(shifted, windows)
    td = windows.clone()
    for i, spec in enumerate(plain.modalities):
        td.set(keys.drop_key(spec.name), torch.full((td.shape[0],), i == 0))
    td.set(keys.DECODE_FROM_PRIOR, torch.ones(td.shape[0], dtype=torch.bool))
    td.set(keys.DECODE_PRIOR_DRAWS, torch.ones(td.shape[0], 2, dtype=torch.bool))
    plain_td = td.clone()
    if posterior_reads == "residual":
        plain_td.set(keys.TARGET, td[keys.TARGET] - cv)
    outs = []
    for model, batch in ((plain, plain_td), (shifted, td)):
        model.train()
        torch.manual_seed(2)
        with torch.no_grad():
            outs.append(model(batch.clone()))
    torch.testing.assert_close(outs[1][keys.POSTERIOR_LOC], outs[0][keys.POSTERIOR_LOC])
    for key in (keys.FORECAST_LOC, keys.FORECAST_DROPPED_LOC, keys.FORECAST_FROM_PRIOR_LOC):
        torch.testing.assert_close(outs[1][key], outs[0][key] + cv)
    torch.testing.assert_close(
        outs[1][keys.FORECAST_FROM_PRIOR_SAMPLES], outs[0][keys.FORECAST_FROM_PRIOR_SAMPLES] + cv[:, None]
    )


def with_another_extrapolation(windows) -> tuple[torch.Tensor, torch.Tensor]:
    """``windows`` with the last step of ``"target_past"`` moved (a new velocity, so a new extrapolation)
    and ``"target"`` moved by as much as the extrapolation: the same residual future."""
    moved = windows.clone()
    past = moved[keys.TARGET_PAST].clone()
    past[:, -1] += torch.tensor([0.5, -0.3])
    moved.set(keys.TARGET_PAST, past)
    horizon = windows[keys.TARGET].shape[1]
    shift = constant_velocity(past, horizon) - constant_velocity(windows[keys.TARGET_PAST], horizon)
    assert shift.abs().min() > 0.1
    moved.set(keys.TARGET, windows[keys.TARGET] + shift)
    return moved


@pytest.mark.parametrize("posterior_reads", ["residual", "target"])
def test_the_posterior_reads_the_residual_future_by_default(data, windows, posterior_reads):
    """Two batches whose futures differ by their extrapolations: the posterior that reads the residual is
    the same for both; the one that reads the target is not."""
    model = forecaster(
        data, decode_from="constant_velocity", prior="learned", posterior_reads=posterior_reads
    )
    with torch.no_grad():
        a, b = model(windows.clone()), model(with_another_extrapolation(windows))
    torch.testing.assert_close(b[keys.PRIOR_LOC], a[keys.PRIOR_LOC])  # X is the same
    same = torch.allclose(b[keys.POSTERIOR_LOC], a[keys.POSTERIOR_LOC], atol=1e-5)
    assert same == (posterior_reads == "residual")


def test_a_few_elbo_steps_on_the_fold_with_a_posterior_of_the_residual(data, windows):
    """The posterior of the residual trains: on real windows the ELBO falls, its KL stays finite and
    positive, and the posterior's target encoder learns."""
    from mmf_rl.objectives import ELBOLoss

    model = forecaster(data, decode_from="constant_velocity", prior="learned").train()
    loss = ELBOLoss(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    encoder_before = [p.detach().clone() for p in model.target_encoder.parameters()]
    totals = []
    for step in range(8):
        torch.manual_seed(step)
        out = loss(windows.clone())
        total = out["loss_nll"] + out["loss_kl"]
        assert torch.isfinite(total) and out["kl"] > 0
        totals.append(total.item())
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
    assert totals[-1] < totals[0]
    assert any(
        not torch.equal(p, q) for p, q in zip(model.target_encoder.parameters(), encoder_before, strict=True)
    )


def test_a_batch_without_target_past_is_refused_naming_the_data_config_key(data, windows):
    model = forecaster(data, decode_from="constant_velocity")
    without = windows.clone().exclude(keys.TARGET_PAST)
    for call in (model, lambda td: model.sample(td, 4)):
        with pytest.raises(
            KeyError,
            match=r"decode_from='constant_velocity' needs 'target_past'.*"
            r"include_target_past: true",
        ):
            call(without.clone())
    assert keys.TARGET_PAST in model.in_keys
    assert keys.TARGET_PAST not in forecaster(data).in_keys


def test_forecast_from_tokens_which_reads_no_past_refuses_the_option(data, windows):
    model = forecaster(data, decode_from="constant_velocity")
    with pytest.raises(ValueError, match=r"forecast_from_tokens: decode_from='constant_velocity'"):
        model.forecast_from_tokens(*model.encode(windows.clone()))


def test_the_option_is_checked_and_a_config_saved_without_it_decodes_from_zero(data):
    config = forecaster(data, decode_from="constant_velocity").config
    saved = {k: v for k, v in config.to_dict().items() if k != "decode_from"}
    assert ForecasterConfig.from_saved_dict(saved).decode_from == "zero"
    # A model saved before posterior_reads existed read the target: it loads reading it still.
    saved = {k: v for k, v in config.to_dict().items() if k != "posterior_reads"}
    assert (config.posterior_reads, ForecasterConfig.from_saved_dict(saved).posterior_reads) == (
        "residual",
        "target",
    )
    assert ForecasterConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match=r"decode_from must be one of \('zero', 'constant_velocity'\)"):
        dataclasses.replace(config, decode_from="cv")
    with pytest.raises(ValueError, match=r"posterior_reads must be one of \('target', 'residual'\)"):
        dataclasses.replace(config, posterior_reads="offset")
    with pytest.raises(ValueError, match=r"needs history >= 2, found history=1"):
        dataclasses.replace(config, history=1)
    with pytest.raises(ValueError, match=r"not supported by a world model .*decode_under_actions"):
        dataclasses.replace(config, action_dim=2, action_steps=config.horizon)


@pytest.mark.slow
@pytest.mark.timeout(1800)  # the fold's conversion, 3 steps and an evaluation: over 10 min under heavy load
def test_a_few_training_steps_on_the_fold_train_and_evaluate(eth, tmp_path):
    import mmf_rl

    path, config = eth
    run = tmp_path / "run"
    mmf_rl.train(
        overrides=[
            f"data={path}",
            f"data.cache_dir={config['cache_dir']}",
            f"data.image_size=[{IMAGE},{IMAGE}]",
            *[f"model.{k}={v}" for k, v in SMALL.items()],
            "model.decode_from=constant_velocity",
            "model.prior=learned",  # its posterior reads the future: the residual one
            f"run_dir={run}",
            "trainer.total_steps=3",
            "trainer.batch_size=16",
            "trainer.eval_every=3",
            "trainer.checkpoint_every=3",
            "trainer.warmup_steps=1",
            "trainer.progress_bar=false",
            "calibrate=false",
            "logger=csv",
            "num_workers=1",
        ]
    )
    saved = load_checkpoint(run / "checkpoints").meta["model_config"]
    assert (saved["decode_from"], saved["posterior_reads"]) == ("constant_velocity", "residual")
    summary = mmf_rl.evaluate(
        overrides=[f"checkpoint={run}", "num_samples=3", "plots=false", "batch_size=64"]
    )
    row, reference = summary["subsets"]["all"], summary["constant_velocity"]
    assert torch.isfinite(torch.tensor([row["ade"], row["min_ade_k"], row["kl"], reference["ade"]])).all()
