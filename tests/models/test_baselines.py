import json

import pytest
import torch
from omegaconf import OmegaConf
from safetensors.torch import load_file, save_file

from mmf_rl import keys
from mmf_rl.configuration import config_dir
from mmf_rl.models import MODELS, build_loss, build_model, model_from_saved_config, saved_config
from mmf_rl.models.baselines.common import zero_filled
from mmf_rl.models.baselines.mvae import product_of_experts
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HISTORY,
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    assert_a_few_steps_reduce_the_loss,
    make_batch,
    presence_patterns,
)

NAMES = [s.name for s in SMALL_MODALITIES]
BASELINES = ["lf_lstm", "mvae", "mult"]
ZERO_FILL = ["lf_lstm", "mult"]
LOSS_CFG = LossConfig()  # beta = 1 without warm-up, L_mis at weight 1
SIZES = {"lf_lstm": {}, "mvae": {"d_latent": 4}, "mult": {"num_heads": 2, "mlp_hidden": 32}}


def make_model(name: str, seed: int = 0):
    torch.manual_seed(seed)
    return build_model(
        {"name": name, "d_model": 16, "head_hidden": 32, **SIZES[name]},
        list(SMALL_MODALITIES),
        HISTORY,
        HORIZON,
        TARGET_DIM,
    )


def with_presence(td, pattern):
    td = td.clone()
    for name in NAMES:
        td.set(keys.present_key(name), torch.full((td.shape[0],), name in pattern))
    return td


def corrupt_absent(td, fill: str):
    """Garbage under every absent modality."""
    td = td.clone()
    g = torch.Generator().manual_seed(3)
    for spec in SMALL_MODALITIES:
        absent = ~td.get(spec.present_key)
        obs = td.get(spec.obs_key)
        if spec.kind == "image":
            junk = torch.randint(1, 256, obs.shape, generator=g, dtype=torch.uint8)
        elif fill == "nan":
            junk = torch.full_like(obs, float("nan"))
        else:
            junk = 1e6 * torch.randn(obs.shape, generator=g)
        obs[absent] = junk[absent]
    return td


@pytest.mark.parametrize("name", BASELINES)
@pytest.mark.parametrize("train", [True, False])
def test_output_shapes_do_not_depend_on_presence(name, train):
    model = make_model(name).train(train)
    batch = make_batch(3)
    for pattern in presence_patterns(NAMES):
        td = with_presence(batch, pattern)
        out = model(td.clone())
        assert out.get(keys.FORECAST_LOC).shape == (3, HORIZON, TARGET_DIM)
        assert out.get(keys.FORECAST_SCALE).shape == (3, HORIZON, TARGET_DIM)
        assert bool((out.get(keys.FORECAST_SCALE) > 0).all())
        samples = model.sample(td.clone(), num_samples=5).get(keys.FORECAST_SAMPLES)
        assert samples.shape == (3, 5, HORIZON, TARGET_DIM)


@pytest.mark.parametrize("name", BASELINES)
def test_mixed_batch_equals_per_sample_results(name, mixed_batch):
    model = make_model(name).eval()
    with torch.no_grad():
        together = model(mixed_batch.clone())
        for i in range(mixed_batch.shape[0]):
            alone = model(mixed_batch[i : i + 1].clone())
            for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
                torch.testing.assert_close(alone.get(key)[0], together.get(key)[i], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", BASELINES)
@pytest.mark.parametrize("fill", ["noise", "nan"])
def test_value_under_absent_modality_changes_nothing(name, fill, mixed_batch):
    model = make_model(name).eval()
    with torch.no_grad():
        reference = model(mixed_batch.clone())
        out = model(corrupt_absent(mixed_batch, fill))
    for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
        assert torch.equal(out.get(key), reference.get(key)), key


@pytest.mark.parametrize("name", ZERO_FILL)
def test_zero_fill_baseline_sees_absent_modality_as_zeros(name, mixed_batch):
    """Absent == present with an all-zero signal (black frames, zero vectors): the zero-fill protocol."""
    model = make_model(name).eval()
    zeroed = mixed_batch.clone()
    for spec in SMALL_MODALITIES:
        zeroed.set(spec.obs_key, zero_filled(mixed_batch, spec))
        zeroed.set(spec.present_key, torch.ones(mixed_batch.shape[0], dtype=torch.bool))
    with torch.no_grad():
        torch.testing.assert_close(
            model(corrupt_absent(mixed_batch, "noise")).get(keys.FORECAST_LOC),
            model(zeroed).get(keys.FORECAST_LOC),
        )


def test_zero_filled_replaces_absent_rows_only():
    batch = corrupt_absent(
        make_batch(
            4,
            present={
                "image": torch.tensor([True, False, True, False]),
                "force": torch.tensor([False, True, True, False]),
            },
        ),
        "nan",
    )
    for spec in SMALL_MODALITIES[:2]:
        filled = zero_filled(batch, spec)
        present = batch.get(spec.present_key)
        assert torch.equal(filled[present], batch.get(spec.obs_key)[present])
        assert not filled[~present].any()


@pytest.mark.parametrize("name", BASELINES)
def test_sample_without_present_modality_is_a_clear_error(name):
    model = make_model(name)
    batch = make_batch(2, present={n: torch.tensor([True, False]) for n in NAMES})
    with pytest.raises(ValueError, match="no present modality"):
        model(batch)


def test_product_of_experts_ignores_absent_experts_and_includes_the_prior():
    loc = torch.tensor([[[2.0], [100.0]]])
    scale = torch.tensor([[[1.0], [0.01]]])
    post_loc, post_scale = product_of_experts(loc, scale, torch.tensor([[True, False]]))
    # N(2, 1) x N(0, 1) = N(1, 1/2)
    torch.testing.assert_close(post_loc, torch.tensor([[1.0]]))
    torch.testing.assert_close(post_scale, torch.tensor([[0.5**0.5]]))
    prior_loc, prior_scale = product_of_experts(loc, scale, torch.tensor([[False, False]]))
    assert torch.equal(prior_loc, torch.zeros(1, 1)) and torch.equal(prior_scale, torch.ones(1, 1))


def test_mvae_gives_no_gradient_to_the_encoder_of_a_modality_absent_from_the_batch():
    model = make_model("mvae").train()
    batch = make_batch(4, present={"image": torch.zeros(4, dtype=torch.bool)})
    build_loss("mvae", model, LOSS_CFG)(batch)["loss_nll"].backward()
    assert all(p.grad is None for p in model.encoders["image"].parameters())
    assert all(p.grad is not None for p in model.encoders["force"].parameters())


@pytest.mark.parametrize("name", BASELINES)
def test_training_steps_reduce_the_loss(name):
    model = make_model(name).train()
    assert_a_few_steps_reduce_the_loss(model, build_loss(name, model, LOSS_CFG))


@pytest.mark.parametrize("name", BASELINES)
def test_registry_build_and_checkpoint_round_trip(name, tmp_path):
    model = make_model(name).eval()
    assert isinstance(model, MODELS[name].model_cls)
    (tmp_path / "config.json").write_text(json.dumps(saved_config(name, model)))
    save_file(model.state_dict(), tmp_path / "model.safetensors")
    rebuilt = model_from_saved_config(json.loads((tmp_path / "config.json").read_text()))
    rebuilt.load_state_dict(load_file(tmp_path / "model.safetensors"))
    rebuilt.eval()
    batch = make_batch(4)
    with torch.no_grad():
        torch.testing.assert_close(
            rebuilt(batch.clone()).get(keys.FORECAST_LOC), model(batch.clone()).get(keys.FORECAST_LOC)
        )


@pytest.mark.parametrize("name", BASELINES)
def test_model_config_file_builds_the_baseline(name):
    cfg = OmegaConf.to_container(OmegaConf.load(config_dir() / "model" / f"{name}.yaml"))
    assert cfg["name"] == name
    model = build_model(cfg, list(SMALL_MODALITIES), HISTORY, HORIZON, TARGET_DIM)
    assert type(model) is MODELS[name].model_cls


@pytest.mark.parametrize("name", BASELINES)
@pytest.mark.parametrize(
    "setting, message",
    [
        ({"d_model": 16.5}, r"Config.d_model must be an integer >= 1, found 16.5"),
        ({"min_scale": -1e-3}, r"Config.min_scale must be > 0 \(the floor of every forecast scale"),
    ],
)
def test_sizes_and_the_scale_floor_are_checked_when_the_config_is_made(name, setting, message):
    with pytest.raises(ValueError, match=message):
        build_model({"name": name, **setting}, list(SMALL_MODALITIES), HISTORY, HORIZON, TARGET_DIM)


def test_unknown_config_key_is_rejected():
    with pytest.raises(ValueError, match="unknown keys"):
        build_model({"name": "lf_lstm", "d_latent": 4}, list(SMALL_MODALITIES), HISTORY, HORIZON, TARGET_DIM)


def test_mvae_refuses_the_gsnn_term_it_cannot_compute():
    with pytest.raises(ValueError, match="gsnn_weight > 0 needs a model that decodes from its prior"):
        build_loss("mvae", make_model("mvae"), LossConfig(gsnn_weight=0.5))
    build_loss("mvae", make_model("mvae"), LossConfig(gsnn_weight=0.0))
