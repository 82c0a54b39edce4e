"""Several tokens per modality, the decoder reading the fused tokens, and decoding at q(z|X)."""

import dataclasses

import pytest
import torch

from mmf_rl import keys
from mmf_rl.eval.metrics import window_metrics
from mmf_rl.models import MultimodalForecaster, build_loss
from mmf_rl.models.encoders import FrameTokens, StepTokens, build_encoder, num_tokens
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HISTORY,
    SMALL_MODALITIES,
    assert_a_few_steps_reduce_the_loss,
    assert_each_sample_alone_gives_its_batch_result,
    make_batch,
)

STEP_MODALITIES = [
    dataclasses.replace(s, encoder="conv_frames" if s.kind == "image" else "steps") for s in SMALL_MODALITIES
]
OUTPUTS = [keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.POSTERIOR_LOC, keys.POSTERIOR_SCALE]


def step_model(small_config, **changes) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, modalities=STEP_MODALITIES, **changes))


def test_step_encoders_emit_one_token_per_step(small_config):
    model = step_model(small_config)
    assert isinstance(model.encoders["image"], FrameTokens)
    assert isinstance(model.encoders["force"], StepTokens)
    assert [num_tokens(model.encoders[s.name]) for s in STEP_MODALITIES] == [HISTORY] * 3
    assert model.token_modality.tolist() == [0] * HISTORY + [1] * HISTORY + [2] * HISTORY
    tokens, present = model.encode(make_batch(4, STEP_MODALITIES))
    assert tokens.shape == (4, 3 * HISTORY, small_config.d_model) and present.shape == (4, 3 * HISTORY)


def test_a_step_token_depends_on_its_step_only(small_config):
    encoder = step_model(small_config).encoders["force"]
    seq = torch.randn(2, HISTORY, 6)
    changed = seq.clone()
    changed[:, 3] += 1.0
    moved = (encoder(changed) - encoder(seq)).abs().amax((0, 2))
    assert bool(moved[3] > 0) and not bool(moved[torch.arange(HISTORY) != 3].any())


def test_linear_step_tokens_are_one_linear_layer_per_step():
    spec = next(dataclasses.replace(s, encoder="linear_steps") for s in STEP_MODALITIES if s.name == "force")
    encoder = build_encoder(spec, HISTORY, 16)
    assert isinstance(encoder, StepTokens) and num_tokens(encoder) == HISTORY
    assert [type(m) for m in encoder.net] == [torch.nn.Linear, torch.nn.ReLU]
    assert encoder(torch.randn(2, HISTORY, 6)).shape == (2, HISTORY, 16)
    with pytest.raises(ValueError, match="per_step must be 'mlp' or 'linear', found 'gru'"):
        StepTokens(spec, HISTORY, 16, per_step="gru")


@pytest.mark.parametrize("decoder_input", ["tokens", "mixed", "pair_streams", "mixed_pair_streams"])
@pytest.mark.parametrize("fusion", ["agnostic", "linear", "average", "sum", "cross_attention"])
def test_step_tokens_keep_the_presence_invariants(small_config, mixed_batch, fusion, decoder_input):
    """A mixed batch gives each sample's own result, and what is stored under an absent modality
    changes nothing, with many tokens per modality as with one."""
    model = step_model(small_config, fusion=fusion, decoder_input=decoder_input).eval()
    batch = make_batch(mixed_batch.shape[0], STEP_MODALITIES, seed=1)
    for spec in STEP_MODALITIES:
        batch.set(spec.present_key, mixed_batch.get(spec.present_key))
    assert_each_sample_alone_gives_its_batch_result(model, batch, OUTPUTS)
    with torch.no_grad():
        together = model(batch.clone())
        corrupted = batch.clone()
        for spec in STEP_MODALITIES:
            absent, obs = ~corrupted.get(spec.present_key), corrupted.get(spec.obs_key)
            obs[absent] = (255 if spec.kind == "image" else 1e6) - obs[absent]
        out = model(corrupted)
    for key in OUTPUTS:
        assert torch.equal(out.get(key), together.get(key)), key


def test_an_encoder_absent_from_the_batch_gets_no_gradient(small_config):
    model = step_model(small_config, decoder_input="mixed").train()
    batch = make_batch(4, STEP_MODALITIES, present={"image": torch.zeros(4, dtype=torch.bool)})
    loss = build_loss("forecaster", model, LossConfig())(batch)
    sum(v for k, v in loss.items() if k.startswith("loss_")).backward()
    assert all(p.grad is None for p in model.encoders["image"].parameters())
    assert all(p.grad is not None for p in model.encoders["force"].parameters())


def test_step_token_model_trains(small_config):
    model = step_model(small_config, decoder_input="mixed").train()
    assert_a_few_steps_reduce_the_loss(model, build_loss("forecaster", model, LossConfig()))


def perturbed_fusion_moves(model: MultimodalForecaster, batch) -> float:
    """Max change of the eval forecast when every weight of the multimodal encoder is perturbed."""
    model.eval()
    with torch.no_grad():
        before = model(batch.clone()).get(keys.FORECAST_LOC)
        for p in model.fusion.parameters():
            p.add_(0.5 * torch.randn_like(p))
        return float((model(batch.clone()).get(keys.FORECAST_LOC) - before).abs().max())


@pytest.mark.parametrize(
    "changes, acts",
    [
        ({"decoder_input": "tokens"}, False),  # the paper read literally: z = 0, the fusion feeds only q(z|X)
        ({}, True),  # the default reads the mixed tokens
        ({"decoder_input": "tokens", "eval_latent": "posterior"}, True),
        ({"decoder_input": "tokens", "prior": "learned"}, True),
        ({"decoder_input": "pair_streams"}, False),  # the pair streams read the raw tokens
        ({"decoder_input": "pair_streams", "eval_latent": "posterior"}, True),
        ({"decoder_input": "pair_streams", "eval_latent": "posterior", "decoder_latent": "none"}, False),
        ({"decoder_input": "mixed_pair_streams", "decoder_latent": "none"}, True),  # streams of mixed tokens
    ],
)
def test_whether_the_fusion_acts_on_eval_forecasts(small_config, changes, acts):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, **changes))
    assert (perturbed_fusion_moves(model, make_batch(4)) > 1e-4) is acts


def test_posterior_eval_latent_decodes_at_the_mean_of_q(small_config):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, eval_latent="posterior")).eval()
    batch = make_batch(4)
    with torch.no_grad():
        out = model(batch.exclude(keys.TARGET))
        tokens, present = model.encode(batch)
        post_loc = out.get(keys.POSTERIOR_LOC)
        expected = model.decode(tokens, present, post_loc)[0]
        torch.testing.assert_close(out.get(keys.LATENT), post_loc)
        torch.testing.assert_close(out.get(keys.FORECAST_LOC), expected)


def test_a_config_saved_before_decoder_input_loads_as_the_raw_tokens(small_config):
    saved = small_config.to_dict()
    del saved["decoder_input"]
    assert small_config.decoder_input == "mixed"
    assert type(small_config).from_saved_dict(saved).decoder_input == "tokens"
    # Plain data is not a saved config: what it lacks takes today's default.
    assert type(small_config).from_dict(saved) == small_config


def test_posterior_eval_latent_needs_a_posterior_without_the_target(small_config):
    with pytest.raises(ValueError, match="eval_latent='posterior'.*posterior_uses_target=false"):
        dataclasses.replace(small_config, eval_latent="posterior", prior="learned")


@pytest.mark.parametrize("prior", ["standard", "learned"])
def test_eval_reports_the_kl_of_the_posterior_to_the_prior(small_config, prior):
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, prior=prior)).eval()
    batch = make_batch(4)
    with torch.no_grad():
        kl = window_metrics(model, batch, lambda y: y)["kl"]
        full = model(batch.clone())
    post = torch.distributions.Normal(full.get(keys.POSTERIOR_LOC), full.get(keys.POSTERIOR_SCALE))
    prior_dist = torch.distributions.Normal(full.get(keys.PRIOR_LOC), full.get(keys.PRIOR_SCALE))
    torch.testing.assert_close(kl, torch.distributions.kl_divergence(post, prior_dist).sum(-1))
    assert bool((kl > 0).all())


def with_step_presence(batch, seed: int = 2):
    """``batch`` with random ``("present_steps", m)``: every sample keeps its last step of each
    modality, so a present modality stays present, and loses some earlier steps."""
    g = torch.Generator().manual_seed(seed)
    out = batch.clone()
    for spec in SMALL_MODALITIES:
        steps = torch.rand(batch.shape[0], HISTORY, generator=g) > 0.4
        steps[:, -1] = True
        out.set(keys.present_steps_key(spec.name), steps)
    return out


def garble_absent_steps(batch):
    out = batch.clone()
    for spec in SMALL_MODALITIES:
        absent, obs = ~out.get(keys.present_steps_key(spec.name)), out.get(spec.obs_key)
        obs[absent] = (255 if spec.kind == "image" else 1e6) - obs[absent]
    return out


@pytest.mark.parametrize("decoder_input", ["mixed", "pair_streams", "mixed_pair_streams"])
@pytest.mark.parametrize("modalities", [SMALL_MODALITIES, STEP_MODALITIES], ids=["window", "steps"])
def test_per_step_presence_keeps_the_invariants(small_config, mixed_batch, modalities, decoder_input):
    """With ``present_steps``: every step present changes nothing, what is stored under an absent step
    changes nothing, and a mixed batch gives each sample its own result."""
    torch.manual_seed(0)
    config = dataclasses.replace(small_config, modalities=modalities, decoder_input=decoder_input)
    model = MultimodalForecaster(config).eval()
    batch = make_batch(mixed_batch.shape[0], modalities, seed=1)
    for spec in modalities:
        batch.set(spec.present_key, mixed_batch.get(spec.present_key))
    all_steps = batch.clone()
    every_step = torch.ones(batch.shape[0], HISTORY, dtype=torch.bool)
    for spec in modalities:
        all_steps.set(keys.present_steps_key(spec.name), every_step)
    partial = with_step_presence(batch)
    with torch.no_grad():
        today, every, some = model(batch.clone()), model(all_steps), model(partial.clone())
        garbled = model(garble_absent_steps(partial))
    for key in OUTPUTS:
        assert torch.equal(every.get(key), today.get(key)), key
        assert torch.equal(garbled.get(key), some.get(key)), key
        assert not torch.equal(some.get(key), today.get(key)), key
    assert_each_sample_alone_gives_its_batch_result(model, partial, OUTPUTS)


def test_an_absent_step_is_an_absent_token_of_a_step_encoder(small_config):
    model = step_model(small_config)
    batch = with_step_presence(make_batch(3, STEP_MODALITIES))
    tokens, present = model.encode(batch)
    steps = torch.cat([batch.get(keys.present_steps_key(s.name)) for s in STEP_MODALITIES], dim=1)
    assert torch.equal(present, steps)
    assert not bool(tokens[~steps].any())


def test_a_window_with_every_step_absent_is_an_absent_modality(small_config):
    model = step_model(small_config)
    batch = make_batch(2, STEP_MODALITIES)
    batch.set(keys.present_steps_key("image"), torch.zeros(2, HISTORY, dtype=torch.bool))
    _, present = model.encode(batch)
    assert torch.equal(model.modality_presence(present), torch.tensor([[False, True, True]] * 2))


def test_per_step_presence_of_a_single_vector_is_a_clear_error():
    with pytest.raises(ValueError, match="windowed modality"):
        keys.zero_absent_steps(torch.zeros(3, 5), torch.ones(3, HISTORY, dtype=torch.bool))
