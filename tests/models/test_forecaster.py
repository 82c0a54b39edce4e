import contextlib
import dataclasses

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HISTORY,
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    assert_a_few_steps_reduce_the_loss,
    assert_each_sample_alone_gives_its_batch_result,
    assert_forecast_under_actions_is_one_forward_per_candidate,
    make_batch,
    presence_patterns,
)

NAMES = [s.name for s in SMALL_MODALITIES]
OUTPUTS = [
    keys.FORECAST_LOC,
    keys.FORECAST_SCALE,
    keys.POSTERIOR_LOC,
    keys.POSTERIOR_SCALE,
    keys.LATENT,
    keys.PRIOR_LOC,
    keys.PRIOR_SCALE,
]
PRIORS = ["standard", "learned"]


@pytest.fixture(params=PRIORS)
def model(request, small_config) -> MultimodalForecaster:
    """The forecaster under each prior: the presence invariants hold for both."""
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, prior=request.param))


@pytest.fixture
def learned_model(small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, prior="learned"))


def with_presence(td, pattern):
    td = td.clone()
    for name in NAMES:
        td.set(keys.present_key(name), torch.full((td.shape[0],), name in pattern))
    return td


@pytest.mark.parametrize("train", [True, False])
def test_output_shapes_do_not_depend_on_presence(model, batch, train):
    model.train(train)
    shapes = set()
    for pattern in presence_patterns(NAMES):
        out = model(with_presence(batch, pattern))
        shapes.add(tuple(tuple(out.get(k).shape) for k in OUTPUTS))
        assert bool((out.get(keys.PRIOR_SCALE) > 0).all() and torch.isfinite(out.get(keys.PRIOR_LOC)).all())
    forecast, latent = (8, HORIZON, TARGET_DIM), (8, 4)
    assert shapes == {(forecast, forecast, latent, latent, latent, latent, latent)}


def test_mixed_batch_equals_per_sample_results(model, mixed_batch):
    assert_each_sample_alone_gives_its_batch_result(model.eval(), mixed_batch, OUTPUTS)


@pytest.mark.parametrize("fill", ["noise", "nan", "zeros"])
def test_value_under_absent_modality_changes_nothing(model, mixed_batch, fill):
    model.eval()
    reference = model(mixed_batch.clone())
    corrupted = mixed_batch.clone()
    g = torch.Generator().manual_seed(3)
    for spec in SMALL_MODALITIES:
        absent = ~corrupted.get(spec.present_key)
        obs = corrupted.get(spec.obs_key)
        if spec.kind == "image":
            junk = (
                torch.randint(0, 256, obs.shape, generator=g, dtype=torch.uint8)
                if fill == "noise"
                else torch.zeros_like(obs)
            )
        else:
            junk = {
                "noise": 1e6 * torch.randn(obs.shape, generator=g),
                "nan": torch.full_like(obs, float("nan")),
                "zeros": torch.zeros_like(obs),
            }[fill]
        obs[absent] = junk[absent]
    out = model(corrupted)
    for key in OUTPUTS:
        assert torch.equal(out.get(key), reference.get(key)), key
    torch.manual_seed(0)
    reference_samples = model.sample(mixed_batch.clone(), num_samples=3).get(keys.FORECAST_SAMPLES)
    torch.manual_seed(0)
    assert torch.equal(model.sample(corrupted, num_samples=3).get(keys.FORECAST_SAMPLES), reference_samples)


def test_no_gradient_reaches_encoder_of_modality_absent_from_whole_batch(model, batch):
    td = batch.clone()
    td.set(keys.present_key("image"), torch.zeros(8, dtype=torch.bool))
    td.set(keys.obs_key("image"), torch.full_like(td.get(keys.obs_key("image")), 255))
    for name in NAMES:  # drop force where the batch has both vectors: the degraded passes too
        td.set(
            keys.drop_key(name),
            torch.arange(8) % 2 == 0 if name == "force" else torch.zeros(8, dtype=torch.bool),
        )
    td.set(keys.DECODE_FROM_PRIOR, torch.ones(8, dtype=torch.bool))
    model.train()
    out = model(td)
    total = sum(
        out.get(k).sum()
        for k in (
            keys.FORECAST_LOC,
            keys.POSTERIOR_LOC,
            keys.PRIOR_LOC,
            keys.FORECAST_DROPPED_LOC,
            keys.FORECAST_FROM_PRIOR_LOC,
        )
    )
    if model.config.prior == "learned":
        total = total + out.get(keys.PRIOR_DROPPED_LOC).sum()
    total.backward()
    assert all(p.grad is None for p in model.encoders["image"].parameters())
    for name in ("force", "proprio"):
        grads = [p.grad for p in model.encoders[name].parameters()]
        assert all(g is not None for g in grads) and any(g.abs().sum() > 0 for g in grads)


def test_zero_present_modalities_is_a_value_error(small_model):
    td = make_batch(2, present={n: torch.tensor([True, False]) for n in NAMES})
    with pytest.raises(ValueError, match=r"have no present modality \(batch indices \[1\]\)"):
        small_model(td)


def test_wrong_dtype_names_key_expected_and_found(small_model, batch):
    batch.set(keys.obs_key("force"), batch.get(keys.obs_key("force")).double())
    with pytest.raises(
        ValueError, match=r"td\[\('obs', 'force'\)\]: expected float32 \[8, 4, 6\], found float64 \[8, 4, 6\]"
    ):
        small_model(batch)


def test_cvae_posterior_needs_the_target_in_training_only(small_config, batch):
    model = MultimodalForecaster(
        ForecasterConfig.from_dict({**small_config.to_dict(), "posterior_uses_target": True})
    )
    del batch[keys.TARGET]
    with pytest.raises(KeyError, match="'target'"):
        model.train()(batch.clone())
    model.eval()(batch.clone())  # inference needs no target


def test_default_posterior_reads_only_the_inputs(small_model, batch):
    small_model.eval()
    with_target = small_model(batch.clone()).get(keys.POSTERIOR_LOC)
    other = batch.clone()
    other.set(keys.TARGET, torch.randn_like(other.get(keys.TARGET)))
    assert torch.equal(small_model(other).get(keys.POSTERIOR_LOC), with_target)
    del other[keys.TARGET]
    assert small_model.train()(other).get(keys.POSTERIOR_LOC).shape == with_target.shape  # no target needed


def test_learned_prior_needs_the_target_in_training_only(learned_model, batch):
    del batch[keys.TARGET]
    with pytest.raises(KeyError, match="'target'"):
        learned_model.train()(batch.clone())
    out = learned_model.eval()(batch.clone())  # inference needs no target, and reports no posterior
    assert keys.POSTERIOR_LOC not in out.keys(include_nested=True)
    assert torch.equal(out.get(keys.LATENT), out.get(keys.PRIOR_LOC))


def test_eval_mean_latent_is_deterministic_and_train_mode_samples(small_model, batch):
    small_model.eval()
    first, second = small_model(batch.clone()), small_model(batch.clone())
    assert torch.equal(first.get(keys.LATENT), torch.zeros(8, 4))
    assert torch.equal(first.get(keys.FORECAST_LOC), second.get(keys.FORECAST_LOC))
    small_model.train()
    z1, z2 = small_model(batch.clone()).get(keys.LATENT), small_model(batch.clone()).get(keys.LATENT)
    assert not torch.equal(z1, z2)


def test_sample_draws_k_prior_forecasts_in_one_pass(small_model, mixed_batch):
    small_model.eval()
    with torch.no_grad():
        out = small_model.sample(mixed_batch.clone(), num_samples=6)
    samples = out.get(keys.FORECAST_SAMPLES)
    assert samples.shape == (mixed_batch.shape[0], 6, HORIZON, TARGET_DIM)
    assert samples.std(dim=1).mean() > 0  # different latents, different forecasts
    # Sample k of element b is the decode of that element with that latent alone.
    torch.manual_seed(5)
    with torch.no_grad():
        out = small_model.sample(mixed_batch.clone(), num_samples=3)
    torch.manual_seed(5)
    z = torch.randn(3 * mixed_batch.shape[0], 4).view(3, mixed_batch.shape[0], 4)
    tokens, present = small_model.encode(mixed_batch)
    with torch.no_grad():
        loc, _ = small_model.decode(tokens, present, z[2])
    torch.testing.assert_close(out.get(keys.FORECAST_SAMPLES)[:, 2], loc, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="num_samples must be >= 1"):
        small_model.sample(mixed_batch.clone(), num_samples=0)


def test_drop_masks_decode_teacher_and_student_in_one_batched_pass(small_model, mixed_batch):
    small_model.train()
    td = mixed_batch.clone()
    present = torch.stack([td.get(keys.present_key(n)) for n in NAMES], 1)
    drop = torch.zeros_like(present)
    multi = present.sum(1) >= 2
    drop[multi, present[multi].float().argmax(1)] = True  # drop the first present modality
    for i, name in enumerate(NAMES):
        td.set(keys.drop_key(name), drop[:, i])
    calls = []
    hook = small_model.decoder.register_forward_hook(lambda mod, args, out: calls.append(args[0].shape[0]))
    out = small_model(td)
    hook.remove()
    assert calls == [2 * td.shape[0]]
    # Teacher = a plain decode with all present modalities; student = decode without the dropped ones.
    tokens, _ = small_model.encode(td)
    z = out.get(keys.LATENT)
    teacher, _ = small_model.decode(tokens, present, z)
    student, _ = small_model.decode(tokens, present & ~drop, z)
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), teacher, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.FORECAST_DROPPED_LOC), student, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(teacher[multi], student[multi])
    assert torch.equal(out.get(keys.FORECAST_DROPPED_LOC)[~multi], out.get(keys.FORECAST_LOC)[~multi])


def test_dropping_every_present_modality_is_refused(small_model, batch):
    for name in NAMES:
        batch.set(keys.drop_key(name), torch.ones(8, dtype=torch.bool))
    with pytest.raises(ValueError, match="removes every present modality"):
        small_model(batch)


@pytest.mark.parametrize("encoder", ["conv", "conv_gru"])
def test_image_encoders_and_vector_modality(encoder):
    specs = [
        ModalitySpec("cam", "image", (3, 16, 16), encoder=encoder, encoder_kwargs={"channels": (4, 8)}),
        ModalitySpec("goal", "vector", (3,)),
    ]
    model = MultimodalForecaster(
        ForecasterConfig(
            modalities=specs,
            history=3,
            horizon=2,
            target_dim=3,
            d_model=8,
            d_latent=2,
            num_heads=2,
            mlp_hidden=8,
            head_hidden=8,
        )
    )
    td = make_batch(5, modalities=specs, history=3, horizon=2, target_dim=3)
    out = model(td)
    assert out.get(keys.FORECAST_LOC).shape == (5, 2, 3)
    assert (out.get(keys.FORECAST_SCALE) > 0).all()


def test_image_size_not_divisible_is_a_clear_error():
    spec = ModalitySpec("cam", "image", (3, 20, 20), encoder_kwargs={"channels": (4, 8, 8)})
    with pytest.raises(ValueError, match="image size 20x20 must be divisible by 8"):
        MultimodalForecaster(ForecasterConfig(modalities=[spec], history=2))


def test_is_a_tensordict_module_with_explicit_keys(small_model, batch):
    assert keys.obs_key("image") in small_model.in_keys and keys.present_key("force") in small_model.in_keys
    assert keys.FORECAST_LOC in small_model.out_keys
    out = TensorDictSequential(small_model.eval())(batch)
    assert out.get(keys.FORECAST_LOC).shape == (8, HORIZON, TARGET_DIM)


def test_config_roundtrip_and_bad_keys(small_config):
    assert ForecasterConfig.from_dict(small_config.to_dict()) == small_config
    with pytest.raises(ValueError, match=r"unknown keys \['d_modle'\]"):
        ForecasterConfig.from_dict({**small_config.to_dict(), "d_modle": 3})
    with pytest.raises(ValueError, match="d_model=10 must be divisible by num_heads=4"):
        ForecasterConfig(modalities=list(SMALL_MODALITIES), d_model=10, num_heads=4)
    with pytest.raises(ValueError, match="modalities is empty"):
        ForecasterConfig()


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"d_model": 16.5}, r"ForecasterConfig.d_model must be an integer >= 1, found 16.5"),
        ({"min_scale": 0.0}, r"ForecasterConfig.min_scale must be > 0 \(the floor of every forecast scale"),
    ],
)
def test_sizes_and_the_scale_floor_are_checked_when_the_config_is_made(setting, message):
    with pytest.raises(ValueError, match=message):
        ForecasterConfig(modalities=list(SMALL_MODALITIES), **setting)


# -- action-conditioned world model ---------------------------------------------------------------

ACTION_SHAPE = (HORIZON, 3)


def with_actions(td, seed: int):
    td = td.clone()
    td.set(
        keys.FUTURE_ACTION,
        torch.randn(td.shape[0], *ACTION_SHAPE, generator=torch.Generator().manual_seed(seed)),
    )
    return td


@pytest.fixture
def world_model(small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(
        dataclasses.replace(small_config, action_steps=ACTION_SHAPE[0], action_dim=ACTION_SHAPE[1])
    )


def test_world_model_forecast_depends_on_the_actions_only_through_them(world_model, batch):
    world_model.eval()
    with torch.no_grad():
        first = world_model(with_actions(batch, 0)).get(keys.FORECAST_LOC)
        again = world_model(with_actions(batch, 0)).get(keys.FORECAST_LOC)
        other = world_model(with_actions(batch, 1)).get(keys.FORECAST_LOC)
    torch.testing.assert_close(first, again)
    assert (first - other).abs().amax(dim=(1, 2)).min() > 1e-4  # every sample's forecast moves


def test_forecast_under_actions_equals_one_forward_per_candidate(world_model, mixed_batch):
    world_model.eval()
    actions = torch.randn(mixed_batch.shape[0], 4, *ACTION_SHAPE, generator=torch.Generator().manual_seed(5))
    assert_forecast_under_actions_is_one_forward_per_candidate(world_model, mixed_batch, actions)


def test_world_model_names_missing_or_malformed_actions(world_model, batch):
    with pytest.raises(KeyError, match="future_action.*float32 \\[B, 5, 3\\]"):
        world_model(batch.clone())
    td = batch.clone()
    td.set(keys.FUTURE_ACTION, torch.zeros(8, 4, 3))
    with pytest.raises(
        ValueError, match=r"td\['future_action'\]: expected float32 \[8, 5, 3\], found float32 \[8, 4, 3\]"
    ):
        world_model(td)
    with pytest.raises(ValueError, match=r"actions: expected \[B, N, S, A\] = \[8, N, 5, 3\]"):
        world_model.forecast_under_actions(batch, torch.zeros(8, 2, 5, 4))


def test_action_fields_go_together_and_a_plain_forecaster_cannot_plan(small_config, small_model, batch):
    with pytest.raises(ValueError, match="action_dim=3 and action_steps=0 must both be > 0"):
        dataclasses.replace(small_config, action_dim=3)
    with pytest.raises(ValueError, match="needs an action-conditioned model"):
        small_model.forecast_under_actions(batch, torch.zeros(8, 2, *ACTION_SHAPE))


def test_world_model_trains_with_both_losses(world_model):
    from mmf_rl.models import build_loss

    loss = build_loss("forecaster", world_model, LossConfig())
    assert_a_few_steps_reduce_the_loss(world_model, loss, action_shape=ACTION_SHAPE)


def action_task(num_samples: int, seed: int, history: int = 2, horizon: int = 6) -> TensorDict:
    """A point whose future is its velocity plus what the (random) actions push it by: the past
    shows the velocity, only the actions show the rest."""
    g = torch.Generator().manual_seed(seed)
    velocity = torch.randn(num_samples, 1, 2, generator=g)
    actions = torch.randn(num_samples, horizon, 2, generator=g)
    steps = torch.arange(1, horizon + 1, dtype=torch.float32)[None, :, None]
    target = 0.1 * velocity * steps + 0.1 * actions.cumsum(1)
    ones = torch.ones(num_samples, dtype=torch.bool)
    return TensorDict(
        {
            keys.obs_key("vel"): velocity.expand(-1, history, -1)
            + 0.05 * torch.randn(num_samples, history, 2, generator=g),
            keys.obs_key("noise"): torch.randn(num_samples, history, 2, generator=g),
            keys.present_key("vel"): ones,
            keys.present_key("noise"): ones.clone(),
            keys.TARGET: target,
            keys.FUTURE_ACTION: actions,
        },
        batch_size=[num_samples],
    )


def with_shuffled_actions(td: TensorDict, seed: int) -> TensorDict:
    """``td`` with its windows' actions permuted among them: actions as varied as before that say
    nothing of the window's pushes."""
    td = td.clone()
    order = torch.randperm(td.shape[0], generator=torch.Generator().manual_seed(seed))
    td.set(keys.FUTURE_ACTION, td.get(keys.FUTURE_ACTION)[order])
    return td


def trained_world_model_error(train: TensorDict, test: TensorDict, steps: int = 100) -> float:
    """The test MSE of a small world model after ``steps`` Adam steps on ``train`` (seed 0)."""
    from mmf_rl.models import build_loss

    torch.manual_seed(0)
    cfg = ForecasterConfig(
        modalities=[ModalitySpec("vel", "sequence", (2,)), ModalitySpec("noise", "sequence", (2,))],
        history=2,
        horizon=6,
        target_dim=2,
        d_model=16,
        d_latent=4,
        num_heads=2,
        mlp_hidden=32,
        head_hidden=32,
        action_steps=6,
        action_dim=2,
    )
    model = MultimodalForecaster(cfg)
    loss = build_loss("forecaster", model, LossConfig())
    optimizer = torch.optim.Adam(model.parameters(), lr=5e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        rows = torch.randint(0, train.shape[0], (64,), generator=g)
        optimizer.zero_grad()
        sum(v for k, v in loss(train[rows]).items() if k.startswith("loss_")).backward()
        optimizer.step()
    model.eval()
    with torch.no_grad():
        return float((model(test.clone()).get(keys.FORECAST_LOC) - test.get(keys.TARGET)).square().mean())


@pytest.mark.slow
def test_world_model_learns_what_the_actions_do():
    """Same data, model and budget: trained and tested with each window's own actions, the forecast
    error falls far below the control's, trained and tested with the actions shuffled among the windows
    (which then must guess the pushes). A model that ignored its actions would score like the control.

    One seed: at this size 100 steps pick the actions up on every seed tried (seeds 0-9 at one and at
    two threads: error ratios 0.25-0.35); the earlier 300 steps at d_model 32 now and then did not
    (0.79 once in ten seeds), which took a median over five seeds."""
    train, test = action_task(1024, seed=0), action_task(256, seed=1)
    own = trained_world_model_error(train, test)
    control = trained_world_model_error(with_shuffled_actions(train, 2), with_shuffled_actions(test, 3))
    # The control learned what the past shows (the velocity): the comparison is of two trained models.
    forecasting_zero = float(test.get(keys.TARGET).square().mean())
    assert control < 0.5 * forecasting_zero, (control, forecasting_zero)
    assert own < 0.5 * control, (own, control)


def test_with_raw_tokens_the_forecast_from_the_prior_does_not_depend_on_the_fusion(small_config, batch):
    """Decoding the raw tokens (the paper read literally), the fusion feeds only q(z|X): eval
    forecasts (z = 0) ignore it; only training sees it."""
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, decoder_input="tokens")).eval()
    with torch.no_grad():
        before = model(batch.clone())
        for parameter in model.fusion.parameters():
            parameter.add_(1.0)
        after = model(batch.clone())
    torch.testing.assert_close(after.get(keys.FORECAST_LOC), before.get(keys.FORECAST_LOC))
    assert not torch.allclose(after.get(keys.POSTERIOR_LOC), before.get(keys.POSTERIOR_LOC))


def test_forecast_from_tokens_is_the_eval_forecast_without_what_it_does_not_read(model, mixed_batch):
    """The lean inference entry (`ForecastTransform` traces it) writes the eval forward's forecast
    for every presence pattern; the multimodal encoder runs only for the learned prior that reads it."""
    model.eval()
    calls = []
    model.fusion.register_forward_hook(lambda *args: calls.append(1))
    with torch.no_grad():
        expected = model(mixed_batch.clone())
        calls.clear()
        loc, scale = model.forecast_from_tokens(*model.encode(mixed_batch))
    assert torch.equal(loc, expected.get(keys.FORECAST_LOC))
    assert torch.equal(scale, expected.get(keys.FORECAST_SCALE))
    assert len(calls) == (model.config.prior == "learned")


# -- learned conditional prior p(z | X) -----------------------------------------------------------


def test_learned_prior_changes_eval_forecasts_through_the_fusion(learned_model, batch):
    """With prior="learned" the multimodal encoder gives z at test time: changing it changes the forecast."""
    learned_model.eval()
    with torch.no_grad():
        before = learned_model(batch.clone())
        for parameter in learned_model.fusion.parameters():
            parameter.add_(1.0)
        after = learned_model(batch.clone())
    assert torch.equal(before.get(keys.LATENT), before.get(keys.PRIOR_LOC))
    assert not torch.allclose(after.get(keys.PRIOR_LOC), before.get(keys.PRIOR_LOC))
    assert (after.get(keys.FORECAST_LOC) - before.get(keys.FORECAST_LOC)).abs().amax(dim=(1, 2)).min() > 1e-6


def test_learned_prior_depends_on_the_present_modalities(learned_model, batch):
    learned_model.eval()
    with torch.no_grad():
        priors = {
            p: learned_model(with_presence(batch, p)).get(keys.PRIOR_LOC) for p in presence_patterns(NAMES)
        }
    patterns = list(priors)
    for i, first in enumerate(patterns):
        for second in patterns[i + 1 :]:
            assert (priors[first] - priors[second]).abs().amax(1).min() > 1e-6, (first, second)
    # The prior reads X only: a different target leaves it unchanged.
    other = batch.clone()
    other.set(keys.TARGET, torch.randn_like(other.get(keys.TARGET)))
    with torch.no_grad():
        torch.testing.assert_close(learned_model(other).get(keys.PRIOR_LOC), priors[tuple(NAMES)])


def test_learned_prior_sample_draws_from_the_prior(learned_model, mixed_batch):
    learned_model.eval()
    b = mixed_batch.shape[0]
    torch.manual_seed(5)
    with torch.no_grad():
        samples = learned_model.sample(mixed_batch.clone(), num_samples=3).get(keys.FORECAST_SAMPLES)
    torch.manual_seed(5)
    noise = torch.randn(3 * b, 4).view(3, b, 4)
    with torch.no_grad():
        tokens, present = learned_model.encode(mixed_batch)
        prior_loc, prior_scale = learned_model.prior(tokens, present)
        loc, _ = learned_model.decode(tokens, present, prior_loc + prior_scale * noise[1])
    torch.testing.assert_close(samples[:, 1], loc, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(prior_loc, learned_model(mixed_batch.clone()).get(keys.PRIOR_LOC))


def drop_first_present_modality(td):
    """Mark the first present modality of every multi-modality row of ``td`` dropped (``("drop", m)``,
    as `MissingModalityLoss` does); returns presence and the drop mask ``[B, M]``."""
    present = torch.stack([td.get(keys.present_key(n)) for n in NAMES], 1)
    drop = torch.zeros_like(present)
    multi = present.sum(1) >= 2
    drop[multi, present[multi].float().argmax(1)] = True
    for i, name in enumerate(NAMES):
        td.set(keys.drop_key(name), drop[:, i])
    return present, drop


def test_degraded_prior_comes_from_the_kept_modalities_in_one_fusion_pass(learned_model, mixed_batch):
    learned_model.train()
    td = mixed_batch.clone()
    present, drop = drop_first_present_modality(td)
    td.set(keys.DECODE_FROM_PRIOR, torch.ones(td.shape[0], dtype=torch.bool))
    fusion_rows, decoder_rows = [], []
    hooks = [
        learned_model.fusion.register_forward_hook(
            lambda mod, args, out: fusion_rows.append(args[0].shape[0])
        ),
        learned_model.decoder.register_forward_hook(
            lambda mod, args, out: decoder_rows.append(args[0].shape[0])
        ),
    ]
    out = learned_model(td)
    for hook in hooks:
        hook.remove()
    b = td.shape[0]
    assert fusion_rows == [2 * b] and decoder_rows == [3 * b]
    tokens, _ = learned_model.encode(td)
    full, degraded = learned_model.prior(tokens, present), learned_model.prior(tokens, present & ~drop)
    torch.testing.assert_close(out.get(keys.PRIOR_LOC), full[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.PRIOR_DROPPED_LOC), degraded[0], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.PRIOR_DROPPED_SCALE), degraded[1], rtol=1e-4, atol=1e-5)
    dropped = drop.any(1)  # the rows with two or more present modalities
    assert not torch.allclose(full[0][dropped], degraded[0][dropped])
    assert out.get(keys.FORECAST_FROM_PRIOR_LOC).shape == (b, HORIZON, TARGET_DIM)


def test_prior_config_choices(small_config):
    learned = dataclasses.replace(small_config, prior="learned")
    assert learned.posterior_reads_target and not small_config.posterior_reads_target
    assert ForecasterConfig.from_dict(learned.to_dict()) == learned
    with pytest.raises(ValueError, match="prior='learned' needs the posterior q\\(z\\|X, y\\)"):
        dataclasses.replace(small_config, prior="learned", posterior_uses_target=False)
    with pytest.raises(ValueError, match="prior must be 'standard' or 'learned', found 'fixed'"):
        dataclasses.replace(small_config, prior="fixed")
    assert MultimodalForecaster(small_config).prior_head is None


def test_learned_prior_model_trains_with_every_loss_option(learned_model):
    from mmf_rl.models import build_loss

    loss = build_loss(
        "forecaster",
        learned_model,
        LossConfig(gsnn_weight=0.5, max_dropped=None, dropped_nll_weight=0.5, dropped_prior_weight=1.0),
    )
    assert {"loss_gsnn", "loss_mis_nll", "loss_mis_prior"} <= set(loss.out_keys)
    elbo, missing = loss.losses
    assert elbo.gsnn_weight == 0.5 and missing.max_dropped is None and missing.dropped_nll_weight == 0.5
    assert_a_few_steps_reduce_the_loss(learned_model, loss)


def test_learned_prior_world_model_plans_from_the_prior_mean(small_config, mixed_batch):
    torch.manual_seed(0)
    model = MultimodalForecaster(
        dataclasses.replace(
            small_config, prior="learned", action_steps=ACTION_SHAPE[0], action_dim=ACTION_SHAPE[1]
        )
    ).eval()
    actions = torch.randn(mixed_batch.shape[0], 3, *ACTION_SHAPE, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        loc, _ = model.forecast_under_actions(mixed_batch, actions)
        for k in range(actions.shape[1]):
            td = mixed_batch.clone()
            td.set(keys.FUTURE_ACTION, actions[:, k])
            torch.testing.assert_close(loc[:, k], model(td).get(keys.FORECAST_LOC), rtol=1e-4, atol=1e-5)


# -- eval_latent="predictive": the moment-matched mixture of K fixed prior draws ------------------

K = 4


@pytest.fixture(params=PRIORS)
def predictive_model(request, small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    config = dataclasses.replace(
        small_config, prior=request.param, eval_latent="predictive", predictive_samples=K
    )
    return MultimodalForecaster(config).eval()


@contextlib.contextmanager
def decoder_rows(model):
    """The row counts of the decoder calls made inside the block."""
    rows = []
    hook = model.decoder.register_forward_hook(lambda mod, args, out: rows.append(args[0].shape[0]))
    try:
        yield rows
    finally:
        hook.remove()


def mixture_moments(locs: torch.Tensor, scales: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and variance of the equal-weight mixture of ``K`` Gaussians ``[K, ...]``, written out."""
    mean = sum(locs) / len(locs)
    variance = sum(s**2 for s in scales) / len(scales) + sum((m - mean) ** 2 for m in locs) / len(locs)
    return mean, variance


def test_predictive_forecast_is_the_mixture_of_k_prior_decodes_in_one_pass(predictive_model, mixed_batch):
    model, b = predictive_model, mixed_batch.shape[0]
    with torch.no_grad():
        with decoder_rows(model) as rows:
            out = model(mixed_batch.clone())
        assert rows == [K * b]
        assert (
            out.get(keys.FORECAST_LOC).shape == out.get(keys.FORECAST_SCALE).shape == (b, HORIZON, TARGET_DIM)
        )
        assert torch.equal(out.get(keys.LATENT), out.get(keys.PRIOR_LOC))
        # The same forecast by an explicit loop over K decodes of z_k = prior mean + prior scale * eps_k.
        tokens, present = model.encode(mixed_batch)
        prior_loc, prior_scale = model.prior(tokens, present)
        decodes = [
            model.decode(tokens, present, prior_loc + prior_scale * eps) for eps in model.predictive_noise
        ]
        locs, scales = torch.stack([d[0] for d in decodes]), torch.stack([d[1] for d in decodes])
    mean, variance = mixture_moments(locs, scales)
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), mean, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.FORECAST_SCALE), variance.sqrt(), rtol=1e-4, atol=1e-5)
    # The spread of the latents widens the forecast beyond the decoder's own scale, never narrows it.
    own = scales.square().mean(0)
    assert bool((out.get(keys.FORECAST_SCALE).square() >= own * (1 - 1e-5)).all())
    assert bool((out.get(keys.FORECAST_SCALE).square() > own * 1.001).any())
    assert not torch.allclose(locs[0], locs[1])  # the K latents differ


def test_predictive_noise_is_fixed_antithetic_and_not_saved(small_config):
    a, b = (
        MultimodalForecaster(
            dataclasses.replace(small_config, eval_latent="predictive", predictive_samples=6)
        )
        for _ in range(2)
    )
    noise = a.predictive_noise
    assert noise.shape == (6, small_config.d_latent) and torch.equal(noise, b.predictive_noise)
    assert torch.equal(noise[3:], -noise[:3]) and noise.abs().min() > 0
    # Not in the state dict: checkpoints written before the option load, and state dicts are unchanged.
    assert not any("predictive_noise" in name for name in a.state_dict())
    MultimodalForecaster(small_config).load_state_dict(a.state_dict())


def test_predictive_forecast_is_deterministic_and_leaves_the_global_rng_alone(predictive_model, batch):
    state = torch.get_rng_state()
    with torch.no_grad():
        first, second = predictive_model(batch.clone()), predictive_model(batch.clone())
    assert torch.equal(torch.get_rng_state(), state)
    for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
        assert torch.equal(first.get(key), second.get(key))
    # The check can see a consumer of the global RNG: a single prior draw is one.
    predictive_model.config.eval_latent = "sample"
    with torch.no_grad():
        predictive_model(batch.clone())
    assert not torch.equal(torch.get_rng_state(), state)


def test_predictive_applies_to_the_degraded_decode_and_not_to_training(predictive_model, mixed_batch):
    model, td = predictive_model, mixed_batch.clone()
    b = td.shape[0]
    present, drop = drop_first_present_modality(td)
    td.set(keys.DECODE_FROM_PRIOR, torch.ones(b, dtype=torch.bool))
    with torch.no_grad():
        with decoder_rows(model) as rows:
            out = model(td.clone())
        assert rows == [2 * K * b + b]  # full and degraded input K times each, the GSNN draw once
        tokens, _ = model.encode(td)
        prior_loc, prior_scale = model.prior(tokens, present)
        decodes = [
            model.decode(tokens, present & ~drop, prior_loc + prior_scale * eps)
            for eps in model.predictive_noise
        ]
    mean, variance = mixture_moments(
        torch.stack([d[0] for d in decodes]), torch.stack([d[1] for d in decodes])
    )
    torch.testing.assert_close(out.get(keys.FORECAST_DROPPED_LOC), mean, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.FORECAST_DROPPED_SCALE), variance.sqrt(), rtol=1e-4, atol=1e-5)
    with decoder_rows(model.train()) as rows:
        model(td.clone())
    assert rows == [3 * b]  # training decodes posterior draws, as before


def test_predictive_world_model_plans_with_k_decodes_per_candidate(small_config, mixed_batch):
    for prior in PRIORS:
        torch.manual_seed(0)
        config = dataclasses.replace(
            small_config,
            prior=prior,
            eval_latent="predictive",
            predictive_samples=K,
            action_steps=ACTION_SHAPE[0],
            action_dim=ACTION_SHAPE[1],
        )
        model = MultimodalForecaster(config).eval()
        b, n = mixed_batch.shape[0], 3
        actions = torch.randn(b, n, *ACTION_SHAPE, generator=torch.Generator().manual_seed(5))
        with torch.no_grad():
            with decoder_rows(model) as rows:
                loc, scale = model.forecast_under_actions(mixed_batch, actions)
            assert rows == [b * n * K], prior
            assert loc.shape == scale.shape == (b, n, HORIZON, TARGET_DIM)
            for k in range(n):
                td = mixed_batch.clone()
                td.set(keys.FUTURE_ACTION, actions[:, k])
                out = model(td)
                torch.testing.assert_close(loc[:, k], out.get(keys.FORECAST_LOC), rtol=1e-4, atol=1e-5)
                torch.testing.assert_close(scale[:, k], out.get(keys.FORECAST_SCALE), rtol=1e-4, atol=1e-5)
            model.config.eval_latent = "mean"
            mean_loc, mean_scale = model.forecast_under_actions(mixed_batch, actions)
        assert not torch.allclose(scale, mean_scale), prior


def test_predictive_config_choices(small_config, small_model, batch):
    assert small_config.eval_latent == "mean" and small_config.predictive_samples == 16
    predictive = dataclasses.replace(small_config, eval_latent="predictive", predictive_samples=8)
    assert ForecasterConfig.from_dict(predictive.to_dict()) == predictive
    saved_before = {k: v for k, v in small_config.to_dict().items() if k != "predictive_samples"}
    assert ForecasterConfig.from_dict(saved_before).predictive_samples == 16  # old checkpoints' configs load
    with pytest.raises(
        ValueError, match=r"eval_latent must be one of \('mean', 'sample', 'predictive', 'posterior'\)"
    ):
        dataclasses.replace(small_config, eval_latent="median")
    for bad in (0, 1, 3, 2.0, "8"):
        with pytest.raises(
            ValueError, match=f"predictive_samples must be an even integer >= 2.*found {bad!r}"
        ):
            dataclasses.replace(small_config, predictive_samples=bad)
    small_model.eval().config.eval_latent = "predictive"
    small_model.config.predictive_samples = 8  # the model was built with 16 fixed draws
    with pytest.raises(ValueError, match="predictive_samples=8 was set after the model was built with 16"):
        small_model(batch.clone())


def test_forecast_from_tokens_moment_matches_like_the_eval_forward(predictive_model, mixed_batch):
    """The lean inference entry honours eval_latent="predictive": the same K draws, the same mixture."""
    with torch.no_grad():
        expected = predictive_model(mixed_batch.clone())
        loc, scale = predictive_model.forecast_from_tokens(*predictive_model.encode(mixed_batch))
    torch.testing.assert_close(loc, expected.get(keys.FORECAST_LOC))
    torch.testing.assert_close(scale, expected.get(keys.FORECAST_SCALE))


# -- tail cuts: ("drop_steps", m) removes a window's last steps from the L_mis student only -------

STEP_TOKEN_MODALITIES = [
    dataclasses.replace(s, encoder="conv_frames" if s.kind == "image" else "steps") for s in SMALL_MODALITIES
]


def tail_cut_batch(modalities, batch_size: int = 12):
    """A mixed-presence batch with partial windows (step 0 always present) and all-False ``("drop", m)``;
    returns it and the ``("drop_steps", m)`` masks it cuts: image rows 0, 3, 6, ... lose their last two
    steps, force rows 1, 4, 7, ... their last step."""
    g = torch.Generator().manual_seed(4)
    td = make_batch(batch_size, modalities, seed=3)
    td.set(keys.present_key("proprio"), torch.arange(batch_size) % 2 == 0)
    cuts = {}
    for offset, (name, length) in enumerate((("image", 2), ("force", 1))):
        steps = torch.rand(batch_size, HISTORY, generator=g) > 0.3
        steps[:, 0] = True
        td.set(keys.present_steps_key(name), steps)
        cut = torch.zeros(batch_size, HISTORY, dtype=torch.bool)
        cut[offset::3, HISTORY - length :] = True
        cuts[name] = cut
    for name in NAMES:
        td.set(keys.drop_key(name), torch.zeros(batch_size, dtype=torch.bool))
    return td, cuts


def with_cuts(td, cuts):
    td = td.clone()
    for name, cut in cuts.items():
        td.set(keys.drop_steps_key(name), cut)
    return td


@pytest.mark.parametrize("decoder_input", ["mixed", "pair_streams", "mixed_pair_streams"])
@pytest.mark.parametrize("prior", PRIORS)
@pytest.mark.parametrize("modalities", [SMALL_MODALITIES, STEP_TOKEN_MODALITIES], ids=["window", "steps"])
def test_a_tail_cut_is_the_student_of_a_window_with_those_steps_absent(
    small_config, modalities, prior, decoder_input
):
    torch.manual_seed(0)
    config = dataclasses.replace(
        small_config, modalities=modalities, prior=prior, decoder_input=decoder_input
    )
    model = MultimodalForecaster(config).eval()
    td, cuts = tail_cut_batch(modalities)
    uncut = td.clone()
    # The same windows with the cut steps marked absent in ("present_steps", m), no masks.
    absent = td.clone().exclude(keys.DROP)
    for name, cut in cuts.items():
        absent.set(keys.present_steps_key(name), td.get(keys.present_steps_key(name)) & ~cut)
    with torch.no_grad():
        out, plain = model(with_cuts(td, cuts)), model(uncut)
        tokens, present = model.encode(absent)
        student, _ = model.decode(tokens, present, out.get(keys.LATENT))
        reference = model(absent.clone())
    for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.LATENT, keys.PRIOR_LOC):
        assert torch.equal(out.get(key), plain.get(key)), key  # the teacher is unchanged
    torch.testing.assert_close(out.get(keys.FORECAST_DROPPED_LOC), student, rtol=1e-4, atol=1e-5)
    if prior == "learned":
        torch.testing.assert_close(
            out.get(keys.PRIOR_DROPPED_LOC), reference.get(keys.PRIOR_LOC), rtol=1e-4, atol=1e-5
        )
    cut_rows = torch.stack([c.any(1) for c in cuts.values()], 1).any(1)
    teacher, dropped = out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_DROPPED_LOC)
    torch.testing.assert_close(
        dropped[~cut_rows], plain.get(keys.FORECAST_DROPPED_LOC)[~cut_rows], rtol=1e-4, atol=1e-5
    )
    assert not torch.allclose(teacher[cut_rows], dropped[cut_rows])


def test_all_false_step_cuts_change_nothing(model):
    td, cuts = tail_cut_batch(SMALL_MODALITIES)
    none_cut = {name: torch.zeros_like(cut) for name, cut in cuts.items()}
    model.train()
    torch.manual_seed(1)
    plain = model(td.clone())
    torch.manual_seed(1)
    masked = model(with_cuts(td, none_cut))
    for key in [*OUTPUTS, keys.FORECAST_DROPPED_LOC, keys.FORECAST_DROPPED_SCALE]:
        assert torch.equal(masked.get(key), plain.get(key)), key


def test_bad_step_cuts_are_clear_errors(small_model):
    td, cuts = tail_cut_batch(SMALL_MODALITIES)
    with pytest.raises(KeyError, match=r"without the \('drop', m\) masks"):
        small_model(with_cuts(td.exclude(keys.DROP), cuts))
    with pytest.raises(ValueError, match=r"expected bool \[12, 4\] for a windowed modality"):
        small_model(with_cuts(td, {"image": cuts["image"][:, :2]}))
    alone = make_batch(
        2, present={"force": torch.zeros(2, dtype=torch.bool), "proprio": torch.zeros(2).bool()}
    )
    for name in NAMES:
        alone.set(keys.drop_key(name), torch.zeros(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="removes every present modality of some sample"):
        small_model(with_cuts(alone, {"image": torch.ones(2, HISTORY, dtype=torch.bool)}))


def test_prior_draws_are_decoded_unmixed_in_the_same_decoder_call(learned_model, mixed_batch):
    model, td = learned_model.train(), mixed_batch.clone()
    b = td.shape[0]
    present, drop = drop_first_present_modality(td)
    td.set(keys.DECODE_FROM_PRIOR, torch.ones(b, dtype=torch.bool))
    torch.manual_seed(4)
    without = model(td.clone())
    td.set(keys.DECODE_PRIOR_DRAWS, torch.ones(b, 3, dtype=torch.bool))
    torch.manual_seed(4)
    with decoder_rows(model) as rows:
        out = model(td.clone())
    assert rows == [2 * b + b + 3 * b]  # teacher, student, the GSNN draw, the K draws
    for key in (keys.FORECAST_LOC, keys.FORECAST_DROPPED_LOC, keys.FORECAST_FROM_PRIOR_LOC):
        torch.testing.assert_close(out.get(key), without.get(key), rtol=1e-4, atol=1e-5)  # drawn after
    # Draw k of row b decodes z = μ_b + σ_b ε_{k * B + b}, ε drawn after the posterior and GSNN draws.
    torch.manual_seed(4)
    torch.randn(b, 4), torch.randn(b, 4)  # the posterior's and the GSNN draws
    noise = torch.randn(3 * b, 4)
    with torch.no_grad():
        tokens, _ = model.encode(td)
        prior_loc, prior_scale = model.prior(tokens, present)
        expected = [model.decode(tokens, present, prior_loc + prior_scale * eps)[0] for eps in noise.split(b)]
    samples = out.get(keys.FORECAST_FROM_PRIOR_SAMPLES)
    assert samples.shape == (b, 3, HORIZON, TARGET_DIM)
    torch.testing.assert_close(samples, torch.stack(expected, 1), rtol=1e-4, atol=1e-5)


def test_prior_draws_stay_unmixed_beside_a_predictive_forecast(predictive_model, batch):
    model = predictive_model.eval()
    with torch.no_grad():
        reference = model(batch.clone())
        td = batch.clone()
        td.set(keys.DECODE_PRIOR_DRAWS, torch.ones(8, 2, dtype=torch.bool))
        with decoder_rows(model) as rows:
            out = model(td)
    assert rows == [K * 8 + 2 * 8]
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), reference.get(keys.FORECAST_LOC))
    torch.testing.assert_close(out.get(keys.FORECAST_SCALE), reference.get(keys.FORECAST_SCALE))
    assert out.get(keys.FORECAST_FROM_PRIOR_SAMPLES).shape == (8, 2, HORIZON, TARGET_DIM)


def test_a_malformed_prior_draws_request_is_a_clear_error(small_model, batch):
    batch.set(keys.DECODE_PRIOR_DRAWS, torch.ones(8, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"td\['decode_prior_draws'\]: expected \[B, K\] with K >= 1"):
        small_model(batch)
