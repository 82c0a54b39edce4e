import dataclasses

import pytest
import torch
import torch.nn.functional as F
from torch.distributions import Normal, kl_divergence

from mmf_rl import keys
from mmf_rl.models import MultimodalForecaster
from mmf_rl.objectives import ELBOLoss, LossConfig
from tests.conftest import small_registered_model


def test_terms_equal_the_distributions_of_the_forward_pass(small_model, batch):
    loss = ELBOLoss(small_model, kl_weight=0.5)
    torch.manual_seed(0)
    out = loss(batch)
    torch.manual_seed(0)
    td = small_model(batch.clone())
    nll = (
        -Normal(td.get(keys.FORECAST_LOC), td.get(keys.FORECAST_SCALE))
        .log_prob(td.get(keys.TARGET))
        .sum((1, 2))
    )
    kl = kl_divergence(
        Normal(td.get(keys.POSTERIOR_LOC), td.get(keys.POSTERIOR_SCALE)),
        Normal(torch.zeros(4), torch.ones(4)),
    ).sum(-1)
    torch.testing.assert_close(out["loss_nll"], nll.mean())
    torch.testing.assert_close(out["loss_kl"], 0.5 * kl.mean())
    torch.testing.assert_close(out["kl"], kl.mean())
    assert out["loss_nll"].requires_grad and not out["kl"].requires_grad


def test_does_not_modify_the_callers_batch(small_model, batch):
    before = set(batch.keys(include_nested=True, leaves_only=True))
    ELBOLoss(small_model)(batch)
    assert set(batch.keys(include_nested=True, leaves_only=True)) == before


def test_kl_warmup_is_linear_and_saved_with_state(small_model, batch):
    loss = ELBOLoss(small_model, kl_weight=2.0, kl_warmup_steps=4)
    weights = []
    for _ in range(6):
        weights.append(float(loss(batch)["kl_weight"]))
    assert weights == [0.5, 1.0, 1.5, 2.0, 2.0, 2.0]
    restored = ELBOLoss(small_model, kl_weight=2.0, kl_warmup_steps=4)
    restored.load_state_dict(loss.state_dict())
    assert int(restored.num_updates) == 6
    with torch.no_grad():
        loss(batch)
    assert int(loss.num_updates) == 6  # evaluation does not advance the schedule


def test_set_keys_reads_a_renamed_target(small_model, batch):
    batch.rename_key_(keys.TARGET, "future")
    loss = ELBOLoss(small_model.eval(), kl_weight=1.0)
    loss.set_keys(target="future")
    assert "future" in loss.in_keys
    # posterior_uses_target reads the contract's "target" key; put it back for the model only.
    batch.set(keys.TARGET, batch.get("future"))
    assert torch.isfinite(loss(batch)["loss_nll"])
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(nope="x")


def test_in_keys_list_the_forecasters_inputs_after_its_own(small_model):
    in_keys = ELBOLoss(small_model).in_keys
    assert in_keys[0] == keys.TARGET and set(small_model.in_keys) <= set(in_keys)
    assert keys.present_key("force") in in_keys


def test_bad_arguments():
    with pytest.raises(ValueError, match="kl_weight and kl_warmup_steps must be >= 0"):
        ELBOLoss(torch.nn.Identity(), kl_weight=-1)
    with pytest.raises(ValueError, match="reduction must be one of"):
        ELBOLoss(torch.nn.Identity(), reduction="max")


def test_reduction_none_gives_per_sample_terms(small_model, batch):
    out = ELBOLoss(small_model, reduction="none")(batch)
    assert out["loss_nll"].shape == (8,) and out["loss_kl"].shape == (8,)


@pytest.fixture
def learned_model(small_config):
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, prior="learned"))


def test_kl_is_to_the_models_learned_prior(learned_model, batch):
    loss = ELBOLoss(learned_model, kl_weight=0.5)
    torch.manual_seed(0)
    out = loss(batch)
    torch.manual_seed(0)
    td = learned_model(batch.clone())
    kl = kl_divergence(
        Normal(td.get(keys.POSTERIOR_LOC), td.get(keys.POSTERIOR_SCALE)),
        Normal(td.get(keys.PRIOR_LOC), td.get(keys.PRIOR_SCALE)),
    ).sum(-1)
    torch.testing.assert_close(out["loss_kl"], 0.5 * kl.mean())
    assert not torch.allclose(td.get(keys.PRIOR_LOC), torch.zeros(8, 4))
    out["loss_kl"].backward()  # the KL trains the prior head too
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in learned_model.prior_head.parameters())


def test_a_model_without_prior_keys_is_scored_against_the_standard_normal(small_model, batch):
    loss = ELBOLoss(small_model)
    td = small_model(batch.clone())
    reference = loss.loss_from_outputs(td)["loss_kl"]
    del td[keys.PRIOR]
    torch.testing.assert_close(loss.loss_from_outputs(td)["loss_kl"], reference)


@pytest.mark.parametrize("prior", ["standard", "learned"])
def test_gsnn_term_is_the_nll_of_a_forecast_decoded_from_the_prior(small_config, batch, prior):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, prior=prior))
    loss = ELBOLoss(model, gsnn_weight=0.25)
    assert "loss_gsnn" in loss.out_keys and keys.FORECAST_FROM_PRIOR_LOC in loss.in_keys
    td = model(loss.prepare(batch.clone()))
    out = loss.loss_from_outputs(td)
    nll = (
        -Normal(td.get(keys.FORECAST_FROM_PRIOR_LOC), td.get(keys.FORECAST_FROM_PRIOR_SCALE))
        .log_prob(td.get(keys.TARGET))
        .sum((1, 2))
    )
    torch.testing.assert_close(out["loss_gsnn"], 0.25 * nll.mean())
    assert not torch.allclose(td.get(keys.FORECAST_FROM_PRIOR_LOC), td.get(keys.FORECAST_LOC))
    assert "loss_gsnn" not in ELBOLoss(model)(batch).keys()  # off by default: no extra decode
    with pytest.raises(ValueError, match="gsnn_weight must be >= 0"):
        ELBOLoss(model, gsnn_weight=-1.0)


def prior_draw_forecasts(model, batch, draws: int, seed: int) -> torch.Tensor:
    """By hand, what the best-of-K request decodes in eval mode (no posterior draw before it):
    ``[K, B, T, D]`` forecast means at ``z_k = μ + σ ε_k`` of the prior, ``ε`` the seed's first draws."""
    torch.manual_seed(seed)
    noise = torch.randn(draws * batch.shape[0], model.config.d_latent)
    tokens, present = model.encode(batch)
    prior_loc, prior_scale = model.prior(tokens, present)
    z = prior_loc.repeat(draws, 1) + prior_scale.repeat(draws, 1) * noise
    loc, _ = model.decode(tokens.repeat(draws, 1, 1), present.repeat(draws, 1), z)
    return loc.unflatten(0, (draws, batch.shape[0]))


@pytest.mark.parametrize("prior", ["standard", "learned"])
def test_best_of_k_term_is_the_mean_over_windows_of_the_closest_prior_draws_mse(small_config, batch, prior):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, prior=prior)).eval()
    loss = ELBOLoss(model, best_of_k_weight=0.5, best_of_k_samples=5)
    assert {"loss_best_of_k", "best_of_k_mse"} <= set(loss.out_keys)
    assert keys.FORECAST_FROM_PRIOR_SAMPLES in loss.in_keys
    torch.manual_seed(1)
    out = loss(batch)
    forecasts = prior_draw_forecasts(model, batch, draws=5, seed=1)
    mse = ((forecasts - batch.get(keys.TARGET)) ** 2).mean((2, 3))  # [K, B]
    expected = torch.tensor([min(mse[:, b].tolist()) for b in range(8)]).mean()
    torch.testing.assert_close(out["loss_best_of_k"], 0.5 * expected)
    torch.testing.assert_close(out["best_of_k_mse"], expected)
    assert out["loss_best_of_k"].requires_grad and not out["best_of_k_mse"].requires_grad
    assert not torch.equal(mse.argmin(0), torch.zeros(8, dtype=torch.long))  # the min picks per window


def test_best_of_one_is_the_mse_of_one_prior_draw(learned_model, batch):
    learned_model.eval()
    torch.manual_seed(3)
    out = ELBOLoss(learned_model, best_of_k_weight=1.0, best_of_k_samples=1)(batch)
    forecast = prior_draw_forecasts(learned_model, batch, draws=1, seed=3)[0]
    torch.testing.assert_close(out["loss_best_of_k"], F.mse_loss(forecast, batch.get(keys.TARGET)))


def test_best_of_k_gradient_reaches_only_the_closest_draw(learned_model, batch):
    loss = ELBOLoss(learned_model, best_of_k_weight=1.0, best_of_k_samples=4)
    td = learned_model.train()(loss.prepare(batch.clone()))
    # Forecasts linear in their latents: d loss / d z_k is non-zero exactly where d loss / d ŷ_k is.
    z = torch.randn(8, 4, 3, requires_grad=True)
    weights = torch.randn(3, td.get(keys.TARGET)[0].numel())
    samples = (z @ weights).unflatten(-1, td.get(keys.TARGET).shape[1:])
    td.set(keys.FORECAST_FROM_PRIOR_SAMPLES, samples)
    loss.loss_from_outputs(td)["loss_best_of_k"].backward()
    closest = ((samples - td.get(keys.TARGET).unsqueeze(1)) ** 2).mean((2, 3)).argmin(1)
    reached = z.grad.abs().sum(-1) > 0  # [B, K]
    assert torch.equal(reached, F.one_hot(closest, 4).bool())


def test_best_of_k_trains_the_learned_prior_through_the_best_draw(learned_model, batch):
    loss = ELBOLoss(learned_model, best_of_k_weight=1.0, best_of_k_samples=3)
    learned_model.train()
    loss(batch)["loss_best_of_k"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in learned_model.prior_head.parameters())


def test_best_of_k_off_adds_no_key_no_decode_and_no_draw(small_model, batch):
    small_model.train()
    torch.manual_seed(0)
    reference = ELBOLoss(small_model)(batch)
    torch.manual_seed(0)
    off = ELBOLoss(small_model, best_of_k_weight=0.0, best_of_k_samples=7)
    assert keys.DECODE_PRIOR_DRAWS not in off.prepare(batch.clone()).keys()
    out = off(batch)
    assert set(out.keys()) == set(reference.keys()) == {"loss_nll", "loss_kl", "kl", "kl_weight"}
    for key in reference.keys():
        torch.testing.assert_close(out[key], reference[key], rtol=0, atol=0)
    # On, its draws come after the posterior's: the ELBO's own terms keep their values.
    torch.manual_seed(0)
    on = ELBOLoss(small_model, best_of_k_weight=1.0, best_of_k_samples=7)(batch)
    for key in ("loss_nll", "loss_kl"):
        torch.testing.assert_close(on[key], reference[key], rtol=0, atol=0)


def test_best_of_k_bad_settings_name_the_setting(small_model):
    with pytest.raises(ValueError, match="best_of_k_weight must be >= 0, found -1.0"):
        ELBOLoss(small_model, best_of_k_weight=-1.0)
    for samples in (0, 2.5):
        with pytest.raises(
            ValueError, match=f"best_of_k_samples must be a whole number >= 1, found {samples}"
        ):
            ELBOLoss(small_model, best_of_k_weight=1.0, best_of_k_samples=samples)


def test_a_model_without_a_prior_decode_refuses_best_of_k():
    mvae = small_registered_model("mvae")
    with pytest.raises(
        ValueError,
        match=r"loss.best_of_k_weight > 0 needs a model that decodes from its prior.*MVAE does not: "
        r"set loss.best_of_k_weight=0",
    ):
        ELBOLoss.from_config(mvae, LossConfig(best_of_k_weight=1.0))
    assert ELBOLoss.from_config(mvae, LossConfig(best_of_k_weight=0.0)).best_of_k_weight == 0.0
