import dataclasses
import json

import pytest
import torch
from safetensors.torch import load_file, save_file

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError, save_checkpoint
from mmf_rl.models import (
    ForecasterConfig,
    MultimodalForecaster,
    build_loss,
    from_pretrained,
    load_trained_model,
    model_from_saved_config,
    saved_config,
)
from mmf_rl.models.fusion import AverageFusion, CrossAttentionFusion, LinearFusion, SumFusion, build_fusion
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    assert_a_few_steps_reduce_the_loss,
    make_batch,
    presence_patterns,
)

NAMES = [s.name for s in SMALL_MODALITIES]
ABLATIONS = ["linear", "average", "sum", "cross_attention"]
OUTPUTS = [keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.POSTERIOR_LOC, keys.POSTERIOR_SCALE]
LOSS_CFG = LossConfig()  # beta = 1 without warm-up, L_mis at weight 1


def make_model(small_config, fusion: str, seed: int = 0) -> MultimodalForecaster:
    torch.manual_seed(seed)
    return MultimodalForecaster(dataclasses.replace(small_config, fusion=fusion))


def with_presence(td, pattern):
    td = td.clone()
    for name in NAMES:
        td.set(keys.present_key(name), torch.full((td.shape[0],), name in pattern))
    return td


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_fusion_replaces_only_the_multimodal_encoder(small_config, fusion):
    paper, ablation = make_model(small_config, "agnostic"), make_model(small_config, fusion)
    assert type(ablation.fusion) is not type(paper.fusion)
    assert type(ablation.decoder) is type(paper.decoder)
    assert set(ablation.encoders) == set(paper.encoders)


@pytest.mark.parametrize("fusion", ABLATIONS)
@pytest.mark.parametrize("train", [True, False])
def test_output_shapes_do_not_depend_on_presence(small_config, batch, fusion, train):
    model = make_model(small_config, fusion).train(train)
    for pattern in presence_patterns(NAMES):
        out = model(with_presence(batch, pattern))
        assert out.get(keys.FORECAST_LOC).shape == (8, HORIZON, TARGET_DIM)
        assert out.get(keys.POSTERIOR_LOC).shape == (8, small_config.d_latent)
        assert bool(torch.isfinite(out.get(keys.POSTERIOR_SCALE)).all())


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_mixed_batch_equals_per_sample_results(small_config, mixed_batch, fusion):
    model = make_model(small_config, fusion).eval()
    with torch.no_grad():
        together = model(mixed_batch.clone())
        for i in range(mixed_batch.shape[0]):
            alone = model(mixed_batch[i : i + 1].clone())
            for key in OUTPUTS:
                torch.testing.assert_close(alone.get(key)[0], together.get(key)[i], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_tokens_of_absent_modalities_change_nothing(fusion):
    """The fusion masks absent tokens itself, whatever the encode step left in them."""
    torch.manual_seed(0)
    module = {
        "linear": LinearFusion(3, 8),
        "average": AverageFusion(),
        "sum": SumFusion(8),
        "cross_attention": CrossAttentionFusion(3, 8, 2, 16),
    }[fusion]
    tokens = torch.randn(7, 3, 8)
    absent = ~torch.tensor([[n in p for n in NAMES] for p in presence_patterns(NAMES)])
    garbage = tokens.masked_fill(absent.unsqueeze(-1), 1e6)
    torch.testing.assert_close(
        module(garbage, absent), module(tokens.masked_fill(absent.unsqueeze(-1), 0), absent)
    )


@pytest.mark.parametrize("fusion", ABLATIONS)
@pytest.mark.parametrize("fill", ["noise", "nan"])
def test_value_under_absent_modality_changes_nothing(small_config, mixed_batch, fusion, fill):
    model = make_model(small_config, fusion).eval()
    reference = model(mixed_batch.clone())
    corrupted = mixed_batch.clone()
    g = torch.Generator().manual_seed(3)
    for spec in SMALL_MODALITIES:
        absent = ~corrupted.get(spec.present_key)
        obs = corrupted.get(spec.obs_key)
        if spec.kind == "image":
            junk = torch.randint(0, 256, obs.shape, generator=g, dtype=torch.uint8)
        else:
            junk = (
                torch.full_like(obs, float("nan"))
                if fill == "nan"
                else 1e6 * torch.randn(obs.shape, generator=g)
            )
        obs[absent] = junk[absent]
    out = model(corrupted)
    for key in OUTPUTS:
        assert torch.equal(out.get(key), reference.get(key)), key


def test_average_and_sum_pool_the_present_tokens():
    tokens = torch.tensor([[[1.0, 2.0, 0.0], [3.0, 4.0, 2.0], [100.0, -50.0, 7.0]]])
    absent = torch.tensor([[False, False, True]])
    torch.testing.assert_close(AverageFusion()(tokens, absent), torch.tensor([[[2.0, 3.0, 1.0]]]))
    sum_fusion = SumFusion(3)
    torch.testing.assert_close(
        sum_fusion(tokens, absent), sum_fusion.output_norm(torch.tensor([[[4.0, 6.0, 2.0]]]))
    )


NORMALISED = ["cross_attention", "linear", "sum"]  # the fusions that end in a LayerNorm


@pytest.mark.parametrize("fusion", NORMALISED)
@pytest.mark.parametrize("token_scale", [1.0, 1e3])
def test_fused_rows_are_layer_normalised_whatever_is_present(fusion, token_scale):
    """The learned prior ties the prior of the full input to that of the input minus dropped
    modalities: their fused features must be on one scale, whatever the number of present
    modalities and the tokens' scale (unnormalised sum/linear/cross-attention collapsed, issue #13).
    At initialisation (unit gain, zero bias) every present row has zero mean and unit variance."""
    torch.manual_seed(0)
    module = build_fusion(fusion, num_modalities=3, d_model=8, num_heads=2, mlp_hidden=16)
    tokens = token_scale * torch.randn(7, 3, 8)
    absent = ~torch.tensor([[n in p for n in NAMES] for p in presence_patterns(NAMES)])
    out = module(tokens.masked_fill(absent.unsqueeze(-1), 0), absent)
    rows = out[~absent] if fusion == "cross_attention" else out.flatten(0, 1)
    torch.testing.assert_close(rows.mean(-1), torch.zeros(len(rows)), atol=1e-5, rtol=0)
    torch.testing.assert_close(rows.var(-1, correction=0), torch.ones(len(rows)), atol=1e-3, rtol=0)
    if fusion == "cross_attention":
        assert not out[absent].any()


@pytest.mark.parametrize("present", [[True, True, True], [True, False, True]])
def test_cross_attention_row_attends_to_the_other_present_modalities(present):
    """Reference: row ``i`` attends, unmasked, to exactly the other present rows."""
    torch.manual_seed(0)
    module = CrossAttentionFusion(3, 8, 2, 16)
    tokens = torch.randn(1, 3, 8)
    absent = ~torch.tensor([present])
    out = module(tokens, absent)
    x = tokens.masked_fill(absent.unsqueeze(-1), 0) + module.modality_embedding
    for i in [i for i in range(3) if present[i]]:
        others = [j for j in range(3) if j != i and present[j]]
        kv = module.norm_kv(x[:, others])
        h = x[:, i : i + 1] + module.attn(module.norm_query(x[:, i : i + 1]), kv, kv)[0]
        expected = module.output_norm(h + module.mlp(module.norm_mlp(h)))
        torch.testing.assert_close(out[:, i : i + 1], expected)
    assert not out[absent].any()


def test_cross_attention_with_a_single_present_modality_is_finite():
    module = CrossAttentionFusion(3, 8, 2, 16)
    out = module(torch.randn(2, 3, 8), torch.tensor([[False, True, True], [True, True, False]]))
    assert bool(torch.isfinite(out).all())


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_training_steps_reduce_the_loss(small_config, fusion):
    model = make_model(small_config, fusion).train()
    assert_a_few_steps_reduce_the_loss(model, build_loss("forecaster", model, LOSS_CFG))


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_registry_checkpoint_round_trip_keeps_the_fusion(small_config, fusion, tmp_path):
    model = make_model(small_config, fusion).eval()
    (tmp_path / "config.json").write_text(json.dumps(saved_config("forecaster", model)))
    save_file(model.state_dict(), tmp_path / "model.safetensors")
    rebuilt = model_from_saved_config(json.loads((tmp_path / "config.json").read_text()))
    assert rebuilt.config.fusion == fusion
    rebuilt.load_state_dict(load_file(tmp_path / "model.safetensors"))
    rebuilt.eval()
    batch = make_batch(4)
    for key in OUTPUTS:
        torch.testing.assert_close(rebuilt(batch.clone()).get(key), model(batch.clone()).get(key))


def without_output_norm(state: dict) -> dict:
    """The weights as saved before the ablation fusions ended in a LayerNorm."""
    return {k: v for k, v in state.items() if not k.startswith("fusion.output_norm.")}


@pytest.mark.parametrize("fusion", NORMALISED)
def test_run_checkpoint_saved_before_the_output_norm_is_a_clear_error(small_config, fusion, tmp_path):
    model = make_model(small_config, fusion)
    meta = {"model_config": saved_config("forecaster", model), "config": {"data": {"root": "data"}}}
    save_checkpoint(tmp_path, 1, without_output_norm(model.state_dict()), meta=meta)
    with pytest.raises(
        CheckpointError,
        match=rf"missing: \['fusion\.output_norm\.bias', 'fusion\.output_norm\.weight'\]\).*"
        rf"saved before the ablation fusions ended in a LayerNorm.*retrain with model\.fusion={fusion}",
    ):
        load_trained_model(tmp_path)


def test_save_pretrained_export_before_the_output_norm_is_a_clear_error(small_config, tmp_path):
    model = make_model(small_config, "sum")
    model.save_pretrained(tmp_path)
    save_file(without_output_norm(load_file(tmp_path / "model.safetensors")), tmp_path / "model.safetensors")
    with pytest.raises(
        CheckpointError, match=r"model\.safetensors does not fit.*retrain with model\.fusion=sum"
    ):
        from_pretrained(tmp_path)


def test_unknown_fusion_is_rejected(small_config):
    with pytest.raises(ValueError, match="fusion must be one of"):
        dataclasses.replace(small_config, fusion="concat")


def test_default_fusion_is_the_papers(small_config):
    assert ForecasterConfig(modalities=list(SMALL_MODALITIES)).fusion == "agnostic"
    assert type(make_model(small_config, "agnostic").fusion).__name__ == "ModalityAgnosticEncoder"
