"""The learned sampler: K codes decoded by the forecaster, presence-safe, and no change to the forecaster."""

import dataclasses

import pytest
import torch

from mmf_rl import keys
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from tests.conftest import make_batch

K = 4


@pytest.fixture
def sampler_model(small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, learned_samples=K)).eval()


def test_a_forecaster_built_with_a_sampler_starts_from_the_same_weights_and_draws(small_config):
    torch.manual_seed(0)
    plain = MultimodalForecaster(small_config)
    after_plain = torch.rand(3)
    torch.manual_seed(0)
    with_sampler = MultimodalForecaster(dataclasses.replace(small_config, learned_samples=K))
    assert torch.equal(torch.rand(3), after_plain)
    sampler_state = with_sampler.state_dict()
    assert {k for k in sampler_state if not k.startswith("latent_sampler.")} == set(plain.state_dict())
    for name, value in plain.state_dict().items():
        assert torch.equal(sampler_state[name], value), name


def test_sampling_k_decodes_the_learned_codes_and_other_counts_draw_from_the_prior(sampler_model, batch):
    with torch.no_grad():
        learned, codes, spreads = sampler_model.learned_samples(batch.clone())
        torch.manual_seed(1)
        first = sampler_model.sample(batch.clone(), K).get(keys.FORECAST_SAMPLES)
        torch.manual_seed(2)
        second = sampler_model.sample(batch.clone(), K).get(keys.FORECAST_SAMPLES)
        prior = sampler_model.sample(batch.clone(), K + 1).get(keys.FORECAST_SAMPLES)
    assert learned.shape == (batch.shape[0], K, *batch.get(keys.TARGET).shape[1:])
    assert codes.shape == spreads.shape == (batch.shape[0], K, sampler_model.config.d_latent)
    torch.testing.assert_close(first, learned)
    torch.testing.assert_close(second, learned)  # deterministic: the codes, not draws around them
    assert prior.shape[1] == K + 1 and not torch.allclose(prior[:, :K], learned)


def test_code_k_decodes_to_the_forecast_of_its_latent(sampler_model, batch):
    """Sample k is the decoder's mean at z = prior mean + prior scale * code k (standard prior: the code)."""
    with torch.no_grad():
        samples, codes, _ = sampler_model.learned_samples(batch.clone())
        tokens, present = sampler_model.encode(batch.clone())
        for k in range(K):
            loc, _ = sampler_model.decode(tokens, present, codes[:, k])
            torch.testing.assert_close(samples[:, k], loc, rtol=1e-4, atol=1e-5)


def test_learned_samples_of_a_mixed_batch_are_each_samples_own(sampler_model, mixed_batch):
    with torch.no_grad():
        together = sampler_model.learned_samples(mixed_batch.clone())[0]
        for i in range(mixed_batch.shape[0]):
            alone = sampler_model.learned_samples(mixed_batch[i : i + 1].clone())[0]
            torch.testing.assert_close(alone[0], together[i], rtol=1e-4, atol=1e-5)


def test_values_under_an_absent_modality_never_change_the_learned_samples(sampler_model):
    present = {"image": torch.tensor([True, False, True, False])}
    batch = make_batch(4, present=present, seed=3)
    changed = batch.clone()
    changed.set(
        ("obs", "image"), torch.randint(0, 256, changed.get(("obs", "image")).shape, dtype=torch.uint8)
    )
    changed.get(("obs", "image"))[present["image"]] = batch.get(("obs", "image"))[present["image"]]
    with torch.no_grad():
        torch.testing.assert_close(
            sampler_model.learned_samples(batch)[0], sampler_model.learned_samples(changed)[0]
        )


def test_the_learned_prior_places_the_codes_in_its_own_coordinates(small_config, batch):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, learned_samples=K, prior="learned")).eval()
    with torch.no_grad():
        samples, codes, _ = model.learned_samples(batch.clone())
        tokens, present = model.encode(batch.clone())
        prior_loc, prior_scale = model.prior(tokens, present)
        loc, _ = model.decode(tokens, present, prior_loc + prior_scale * codes[:, 2])
    torch.testing.assert_close(samples[:, 2], loc, rtol=1e-4, atol=1e-5)


def test_a_forecaster_without_a_sampler_says_how_to_get_one(small_model, batch):
    with pytest.raises(ValueError, match="model.learned_samples=K"):
        small_model.learned_samples(batch)


@pytest.mark.parametrize("value", [-1, True, 2.5])
def test_learned_samples_must_be_a_whole_number(small_config, value):
    with pytest.raises(ValueError, match="learned_samples must be a whole number >= 0"):
        ForecasterConfig(**{**dataclasses.asdict(small_config), "learned_samples": value})


def test_drawing_from_the_prior_sets_the_sampler_aside_for_a_while(sampler_model, batch):
    with torch.no_grad():
        learned = sampler_model.learned_samples(batch.clone())[0]
        with sampler_model.drawing_from_the_prior() as model:
            torch.manual_seed(3)
            drawn = model.sample(batch.clone(), K).get(keys.FORECAST_SAMPLES)
        torch.manual_seed(3)
        with pytest.raises(RuntimeError, match="inside"), sampler_model.drawing_from_the_prior():
            raise RuntimeError("inside")
        again = sampler_model.sample(batch.clone(), K).get(keys.FORECAST_SAMPLES)
    assert not torch.allclose(drawn, learned)
    torch.testing.assert_close(again, learned)
