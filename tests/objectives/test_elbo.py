import dataclasses

import pytest
import torch
from torch.distributions import Normal, kl_divergence

from mmf_rl import keys
from mmf_rl.models import MultimodalForecaster
from mmf_rl.objectives import ELBOLoss


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
