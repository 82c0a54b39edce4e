"""DLow's objective: each term as its formula says, the drops it makes, and a sampler that learns from it."""

import dataclasses

import pytest
import torch

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import DiverseSamplingLoss
from tests.conftest import make_batch

K = 4


@pytest.fixture
def sampler_model(small_config) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, learned_samples=K)).eval()


def test_each_term_is_its_formula_in_the_targets_units(sampler_model, batch):
    scale = torch.tensor([2.0, 0.5])
    loss = DiverseSamplingLoss(
        sampler_model,
        target_scale=scale,
        diversity_weight=3.0,
        diversity_scale=7.0,
        kl_floor=0.0,
        drop_prob=0.0,
    )
    out = loss(batch)
    samples, codes, spreads = sampler_model.learned_samples(batch.clone())
    forecasts, target = samples * scale, batch.get(keys.TARGET) * scale
    best = torch.stack([(forecasts[:, k] - target).square().sum((-2, -1)) for k in range(K)], 1).amin(1)
    pairs = [(j, k) for j in range(K) for k in range(j + 1, K)]
    close = torch.stack(
        [(-(forecasts[:, j] - forecasts[:, k]).square().sum((-2, -1)) / 7.0).exp() for j, k in pairs], 1
    )
    var = spreads.square() + 1e-8
    kl = (0.5 * (var + codes.square() - 1 - var.log())).sum((1, 2))
    torch.testing.assert_close(out["loss_best_of_k"], 5.0 * best.mean())
    torch.testing.assert_close(out["loss_diversity"], 3.0 * close.mean())
    torch.testing.assert_close(out["loss_kl"], 0.1 * kl.mean())


def test_the_kl_term_is_flat_below_its_floor(sampler_model, batch):
    loss = DiverseSamplingLoss(sampler_model, kl_floor=1e6, drop_prob=0.0)
    assert float(loss(batch)["loss_kl"].detach()) == pytest.approx(0.1 * 1e6)


def test_drops_keep_one_modality_never_a_required_one_and_never_revive_an_absent_one(small_config):
    specs = [dataclasses.replace(s, required=s.name == "force") for s in small_config.modalities]
    torch.manual_seed(0)
    model = MultimodalForecaster(dataclasses.replace(small_config, modalities=specs, learned_samples=K))
    loss = DiverseSamplingLoss(model, drop_prob=0.9)
    present = {"image": torch.arange(64) % 2 == 0, "proprio": torch.arange(64) % 3 == 0}
    batch = make_batch(64, modalities=specs, present=present)
    torch.manual_seed(1)
    dropped = loss.prepare(batch.clone())
    kept = torch.stack([dropped.get(s.present_key) for s in specs], -1)
    before = torch.stack([batch.get(s.present_key) for s in specs], -1)
    assert kept.any(-1).all()
    assert not (kept & ~before).any()
    assert torch.equal(dropped.get(("present", "force")), batch.get(("present", "force")))
    assert (before & ~kept).any()  # something was dropped


def test_only_the_sampler_learns_and_its_loss_falls(sampler_model):
    batch = make_batch(16, seed=4)
    # A heavy diversity term: an untrained decoder barely reads z, which bounds what the codes can reach.
    loss = DiverseSamplingLoss(
        sampler_model, diversity_weight=20.0, diversity_scale=10.0, drop_prob=0.0
    ).train()
    assert not sampler_model.training and sampler_model.latent_sampler.training
    before_state = {k: v.clone() for k, v in sampler_model.state_dict().items()}
    sampler_model.requires_grad_(False).latent_sampler.requires_grad_(True)
    optimizer = torch.optim.Adam(sampler_model.latent_sampler.parameters(), lr=1e-2)

    def total():
        return sum(v for k, v in loss(batch).items() if k.startswith("loss_"))

    first = float(total().detach())
    for _ in range(30):
        optimizer.zero_grad()
        total().backward()
        optimizer.step()
    assert float(total().detach()) < 0.95 * first
    for name, value in sampler_model.state_dict().items():
        assert torch.equal(value, before_state[name]) == (not name.startswith("latent_sampler.")), name


def test_a_forecaster_without_a_sampler_is_refused(small_model):
    with pytest.raises(ValueError, match="learned_samples=K > 0"):
        DiverseSamplingLoss(small_model)


def test_a_lone_required_modality_is_never_dropped():
    spec = ModalitySpec("force", "sequence", (6,), required=True)
    torch.manual_seed(0)
    cfg = ForecasterConfig(
        modalities=[spec],
        history=4,
        horizon=5,
        d_model=16,
        d_latent=4,
        num_heads=2,
        mlp_hidden=32,
        head_hidden=32,
        learned_samples=K,
    )
    loss = DiverseSamplingLoss(MultimodalForecaster(cfg), drop_prob=0.9)
    batch = make_batch(32, modalities=[spec])
    assert loss.prepare(batch.clone()).get(("present", "force")).all()
