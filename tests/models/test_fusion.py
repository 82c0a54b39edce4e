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
    load_trained_model,
    model_from_saved_config,
    saved_config,
)
from mmf_rl.models.fusion import (
    FUSIONS,
    AverageFusion,
    CrossAttentionFusion,
    FusionShape,
    SumFusion,
    build_fusion,
    register_fusion,
)
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    assert_a_few_steps_reduce_the_loss,
    assert_each_sample_alone_gives_its_batch_result,
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


def shape(num_tokens: int = 3, role: str = "encoder") -> FusionShape:
    return FusionShape(
        num_modalities=3,
        num_tokens=num_tokens,
        d_model=8,
        num_heads=2,
        mlp_hidden=16,
        num_layers=2,
        role=role,
    )


ONE_TOKEN_EACH = torch.arange(3)


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_fusion_swaps_the_aggregation_in_both_places(small_config, fusion):
    paper, ablation = make_model(small_config, "agnostic"), make_model(small_config, fusion)
    assert type(ablation.fusion) is type(ablation.decoder.fusion) is type(build_fusion(fusion, shape()))
    assert paper.decoder.fusion is None  # the paper's own attention from P^D (eqs. 12-14)
    assert not hasattr(ablation.decoder, "aggregate") and not hasattr(ablation.decoder, "refine")
    assert set(ablation.encoders) == set(paper.encoders)


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_every_fusion_hands_the_heads_the_same_features(small_config, fusion):
    paper, ablation = make_model(small_config, "agnostic"), make_model(small_config, fusion)
    assert ablation.posterior_head[0].in_features == paper.posterior_head[0].in_features
    assert ablation.decoder.head[0].in_features == paper.decoder.head[0].in_features


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
    assert_each_sample_alone_gives_its_batch_result(
        make_model(small_config, fusion).eval(), mixed_batch, OUTPUTS
    )


@pytest.mark.parametrize("fusion", ABLATIONS)
def test_tokens_of_absent_modalities_change_nothing(fusion):
    """The fusion masks absent tokens itself, whatever the encode step left in them."""
    torch.manual_seed(0)
    module = build_fusion(fusion, shape())
    tokens = torch.randn(7, 3, 8)
    absent = ~torch.tensor([[n in p for n in NAMES] for p in presence_patterns(NAMES)])
    garbage = tokens.masked_fill(absent.unsqueeze(-1), 1e6)
    torch.testing.assert_close(
        module(garbage, absent, ONE_TOKEN_EACH),
        module(tokens.masked_fill(absent.unsqueeze(-1), 0), absent, ONE_TOKEN_EACH),
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
    average = AverageFusion(shape())(tokens, absent, ONE_TOKEN_EACH)
    torch.testing.assert_close(average, torch.tensor([[[2.0, 3.0, 1.0]]]).expand(1, 3, 3))
    sum_fusion = SumFusion(dataclasses.replace(shape(), d_model=3))
    torch.testing.assert_close(
        sum_fusion(tokens, absent, ONE_TOKEN_EACH),
        sum_fusion.output_norm(torch.tensor([[[4.0, 6.0, 2.0]]])).expand(1, 3, 3),
    )


NORMALISED = ["cross_attention", "linear", "sum"]  # the fusions that end in a LayerNorm


@pytest.mark.parametrize("fusion", NORMALISED)
@pytest.mark.parametrize("token_scale", [1.0, 1e3])
def test_fused_rows_are_layer_normalised_whatever_is_present(fusion, token_scale):
    """The learned prior ties the prior of the full input to that of the input minus dropped
    modalities: their fused features must be on one scale, whatever the number of present
    modalities and the tokens' scale (unnormalised, the sum, linear and cross-attention fusions
    collapsed: docs/results.md). At initialisation (unit gain, zero bias) every present row has zero
    mean and unit variance."""
    torch.manual_seed(0)
    module = build_fusion(fusion, shape())
    tokens = token_scale * torch.randn(7, 3, 8)
    absent = ~torch.tensor([[n in p for n in NAMES] for p in presence_patterns(NAMES)])
    out = module(tokens.masked_fill(absent.unsqueeze(-1), 0), absent, ONE_TOKEN_EACH)
    rows = out[~absent] if fusion == "cross_attention" else out.flatten(0, 1)
    torch.testing.assert_close(rows.mean(-1), torch.zeros(len(rows)), atol=1e-5, rtol=0)
    torch.testing.assert_close(rows.var(-1, correction=0), torch.ones(len(rows)), atol=1e-3, rtol=0)
    if fusion == "cross_attention":
        assert not out[absent].any()


@pytest.mark.parametrize("present", [[True, True, True], [True, False, True]])
def test_cross_attention_row_attends_to_the_other_present_modalities(present):
    """Reference: row ``i`` attends, unmasked, to exactly the other present rows."""
    torch.manual_seed(0)
    module = CrossAttentionFusion(shape())
    tokens = torch.randn(1, 3, 8)
    absent = ~torch.tensor([present])
    out = module(tokens, absent, ONE_TOKEN_EACH)
    x = tokens.masked_fill(absent.unsqueeze(-1), 0) + module.modality_embedding
    for i in [i for i in range(3) if present[i]]:
        others = [j for j in range(3) if j != i and present[j]]
        kv = module.norm_kv(x[:, others])
        h = x[:, i : i + 1] + module.attn(module.norm_query(x[:, i : i + 1]), kv, kv)[0]
        expected = module.output_norm(h + module.mlp(module.norm_mlp(h)))
        torch.testing.assert_close(out[:, i : i + 1], expected)
    assert not out[absent].any()


def test_cross_attention_with_a_single_present_modality_is_finite():
    module = CrossAttentionFusion(shape())
    absent = torch.tensor([[False, True, True], [True, True, False]])
    out = module(torch.randn(2, 3, 8), absent, ONE_TOKEN_EACH)
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


def test_checkpoint_of_a_posterior_only_ablation_is_a_clear_error(small_config, tmp_path):
    """Ablation weights saved when the ablation replaced only the posterior's fusion (the decoder kept
    the paper's attention) do not fit a model whose decoder aggregates with the ablation too."""
    model = make_model(small_config, "sum")
    state = {k: v for k, v in model.state_dict().items() if not k.startswith("decoder.fusion.")}
    state |= {f"decoder.{k}": v for k, v in make_model(small_config, "agnostic").decoder.state_dict().items()}
    meta = {"model_config": saved_config("forecaster", model), "config": {"data": {"root": "data"}}}
    save_checkpoint(tmp_path, 1, state, meta=meta)
    with pytest.raises(
        CheckpointError, match=r"replaced only the posterior's fusion.*retrain with model\.fusion=sum"
    ):
        load_trained_model(tmp_path)


def test_a_new_fusion_is_one_module_and_one_registration(small_config):
    @register_fusion("first_token")
    class FirstToken(torch.nn.Module):
        def __init__(self, shape: FusionShape):
            super().__init__()
            self.out_rows = shape.num_modalities

        def forward(self, tokens, absent, token_modality):
            return tokens[:, :1].expand(-1, self.out_rows, -1)

    try:
        model = make_model(small_config, "first_token").eval()
        assert model(make_batch(2)).get(keys.FORECAST_LOC).shape == (2, HORIZON, TARGET_DIM)
    finally:
        del FUSIONS["first_token"]


def test_unknown_fusion_is_rejected(small_config):
    with pytest.raises(ValueError, match=r"unknown fusion 'concat'; expected one of \['agnostic', 'average'"):
        dataclasses.replace(small_config, fusion="concat")


def test_default_fusion_is_the_papers(small_config):
    assert ForecasterConfig(modalities=list(SMALL_MODALITIES)).fusion == "agnostic"
    assert type(make_model(small_config, "agnostic").fusion).__name__ == "ModalityAgnosticEncoder"
