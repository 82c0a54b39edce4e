import dataclasses

import pytest
import torch
from tensordict import TensorDict
from torch.distributions import Normal, kl_divergence

from mmf_rl import keys
from mmf_rl.models import MultimodalForecaster
from mmf_rl.objectives import CombinedLoss, ELBOLoss, MissingModalityLoss
from tests.conftest import SMALL_MODALITIES, make_batch

NAMES = [s.name for s in SMALL_MODALITIES]


def outputs(teacher_loc, student_loc, drop_first=True):
    b = teacher_loc.shape[0]
    td = TensorDict(
        {
            keys.FORECAST_LOC: teacher_loc,
            keys.FORECAST_SCALE: torch.ones_like(teacher_loc),
            keys.FORECAST_DROPPED_LOC: student_loc,
            keys.FORECAST_DROPPED_SCALE: torch.ones_like(student_loc),
        },
        batch_size=[b],
    )
    for i, name in enumerate(NAMES):
        td.set(keys.drop_key(name), torch.full((b,), drop_first and i == 0))
    return td


def test_loss_is_zero_when_masked_decode_equals_full_and_positive_otherwise(small_model):
    loss = MissingModalityLoss(small_model)
    loc = torch.randn(4, 5, 2)
    assert loss.loss_from_outputs(outputs(loc, loc.clone()))["loss_mis"] == 0
    shifted = loss.loss_from_outputs(outputs(loc, loc + 0.5))["loss_mis"]
    # KL(N(a,1) || N(a+0.5,1)) = 0.125 per element, 10 elements per sample.
    torch.testing.assert_close(shifted, torch.tensor(1.25))


def test_samples_with_nothing_dropped_do_not_count(small_model):
    loss = MissingModalityLoss(small_model)
    loc = torch.randn(4, 5, 2)
    out = loss.loss_from_outputs(outputs(loc, loc + 0.5, drop_first=False))
    assert out["loss_mis"] == 0 and out["mis_fraction"] == 0


def test_prepare_drops_exactly_one_present_modality_where_two_or_more(small_model):
    present = {
        "image": torch.tensor([1, 1, 0, 1, 0] * 400).bool(),
        "force": torch.tensor([1, 0, 0, 1, 1] * 400).bool(),
        "proprio": torch.tensor([1, 0, 1, 1, 0] * 400).bool(),
    }
    td = make_batch(2000, present=present)
    loss = MissingModalityLoss(small_model)
    torch.manual_seed(0)
    loss.prepare(td)
    drop = torch.stack([td.get(keys.drop_key(n)) for n in NAMES], 1)
    pres = torch.stack([present[n] for n in NAMES], 1)
    assert not (drop & ~pres).any()  # only present modalities are dropped
    assert torch.equal(drop.sum(1), (pres.sum(1) >= 2).long())  # one where possible, none otherwise
    # Uniform over the present ones: all three present in rows 3, 8, ... -> each ~1/3.
    shares = drop[3::5].float().mean(0)
    assert torch.allclose(shares, torch.full((3,), 1 / 3), atol=0.06)
    torch.manual_seed(0)
    again = loss.prepare(make_batch(2000, present=present))
    assert torch.equal(drop, torch.stack([again.get(keys.drop_key(n)) for n in NAMES], 1))


def test_end_to_end_loss_is_positive_and_trains_the_student_only(small_model, batch):
    small_model.train()
    out = MissingModalityLoss(small_model, weight=2.0)(batch)
    assert out["loss_mis"] > 0 and out["mis_fraction"] == 1
    torch.testing.assert_close(out["loss_mis"], 2.0 * out["mis_kl"])
    out["loss_mis"].backward()
    # The teacher is detached: gradients still flow (through the student), and stay finite.
    grads = [p.grad for p in small_model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_detached_teacher_gets_no_gradient_from_loss_mis(small_model):
    loc = torch.randn(4, 5, 2, requires_grad=True)
    student = torch.randn(4, 5, 2, requires_grad=True)
    for detach, teacher_has_grad in ((True, False), (False, True)):
        loc.grad = None
        MissingModalityLoss(small_model, detach_teacher=detach).loss_from_outputs(outputs(loc, student))[
            "loss_mis"
        ].backward()
        assert (loc.grad is not None) == teacher_has_grad
        assert student.grad is not None


def test_combined_loss_runs_the_forecaster_once(small_model, batch):
    calls = []
    handle = small_model.register_forward_hook(lambda *args: calls.append(1))
    combined = CombinedLoss(ELBOLoss(small_model), MissingModalityLoss(small_model))
    out = combined(batch)
    handle.remove()
    assert len(calls) == 1
    assert {"loss_nll", "loss_kl", "loss_mis"} <= set(out.keys())
    assert set(combined.out_keys) >= {"loss_nll", "loss_kl", "loss_mis"}


def test_combined_teacher_equals_plain_elbo_forward(small_model, batch):
    torch.manual_seed(1)
    plain = ELBOLoss(small_model)(batch)
    torch.manual_seed(1)
    td = batch.clone()
    z_state = torch.get_rng_state()
    combined = CombinedLoss(ELBOLoss(small_model), MissingModalityLoss(small_model))
    # prepare() draws its random choice first; replay the plain run's RNG for the latent.
    td = combined.prepare(td)
    torch.set_rng_state(z_state)
    out = combined.loss_from_outputs(small_model(td))
    torch.testing.assert_close(out["loss_nll"], plain["loss_nll"])


def test_combined_loss_refuses_different_forecasters(small_model, small_config):
    from mmf_rl.models import MultimodalForecaster

    with pytest.raises(ValueError, match="same forecaster"):
        CombinedLoss(ELBOLoss(small_model), MissingModalityLoss(MultimodalForecaster(small_config)))


def test_presence_keys_come_from_the_forecaster_and_can_be_pointed_elsewhere(small_model):
    loss = MissingModalityLoss(small_model)
    defaults = {n: keys.present_key(n) for n in NAMES}
    assert loss.tensor_keys.present == defaults and set(defaults.values()) <= set(loss.in_keys)
    loss.set_keys(present={"image": "image_may_drop"})
    assert loss.tensor_keys.present == {**defaults, "image": "image_may_drop"}
    assert "image_may_drop" in loss.in_keys
    td = make_batch(64)
    td.set("image_may_drop", torch.zeros(64, dtype=torch.bool))
    torch.manual_seed(0)
    loss.prepare(td)
    assert not td.get(keys.drop_key("image")).any()
    assert (td.get(keys.drop_key("force")) | td.get(keys.drop_key("proprio"))).all()
    loss.set_keys(present=None)
    assert loss.tensor_keys.present == defaults
    with pytest.raises(ValueError, match=r"\['lidar'\] are not modalities of the forecaster"):
        loss.set_keys(present={"lidar": ("present", "lidar")})


THREE_PATTERNS = {
    "image": torch.tensor([1, 1, 0, 1, 0] * 400).bool(),
    "force": torch.tensor([1, 0, 0, 1, 1] * 400).bool(),
    "proprio": torch.tensor([1, 0, 1, 1, 0] * 400).bool(),
}


def drawn_drops(loss, seed=0):
    td = make_batch(2000, present=THREE_PATTERNS)
    torch.manual_seed(seed)
    loss.prepare(td)
    return torch.stack([td.get(keys.drop_key(n)) for n in NAMES], 1)


@pytest.mark.parametrize("max_dropped", [None, 2])
def test_uniform_drop_count_trains_single_modality_inputs(small_model, max_dropped):
    drop = drawn_drops(MissingModalityLoss(small_model, max_dropped=max_dropped))
    present = torch.stack([THREE_PATTERNS[n] for n in NAMES], 1)
    kept = present & ~drop
    assert not (drop & ~present).any() and bool(kept.any(1).all())  # only present ones, never all of them
    assert torch.equal(
        drop.sum(1)[present.sum(1) <= 2], (present.sum(1)[present.sum(1) <= 2] - 1).clamp_min(0)
    )
    full = (
        present.sum(1) == 3
    )  # rows 0, 3, 5, 8, ...: one or two of three dropped, each count about half the time
    counts = drop[full].sum(1)
    assert set(counts.tolist()) == {1, 2}
    assert abs(float((counts == 2).float().mean()) - 0.5) < 0.05
    # Single-modality inputs occur in the rows that had all three; each modality is dropped about
    # half the time.
    assert (kept[full].sum(1) == 1).any()
    torch.testing.assert_close(drop[full].float().mean(0), torch.full((3,), 0.5), atol=0.06, rtol=0)


def test_max_dropped_one_is_the_papers_setting_and_caps_apply(small_model):
    default = drawn_drops(MissingModalityLoss(small_model))
    assert torch.equal(drawn_drops(MissingModalityLoss(small_model, max_dropped=1)), default)
    assert int(default.sum(1).max()) == 1
    with pytest.raises(ValueError, match="max_dropped must be >= 1"):
        MissingModalityLoss(small_model, max_dropped=0)


def test_nll_of_the_degraded_forecast_counts_dropped_samples_only(small_model):
    loss = MissingModalityLoss(small_model, dropped_nll_weight=0.5)
    assert "loss_mis_nll" in loss.out_keys and "loss_mis_nll" not in MissingModalityLoss(small_model).out_keys
    loc = torch.randn(4, 5, 2)
    td = outputs(loc, loc + 0.5)
    td.set(keys.TARGET, torch.randn(4, 5, 2))
    td.set(keys.drop_key(NAMES[0]), torch.tensor([True, True, False, False]))
    nll = -Normal(loc + 0.5, torch.ones_like(loc)).log_prob(td.get(keys.TARGET)).sum((1, 2))
    torch.testing.assert_close(loss.loss_from_outputs(td)["loss_mis_nll"], 0.5 * nll[:2].mean())


@pytest.fixture
def learned_model(small_config):
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, prior="learned"))


def test_prior_of_the_degraded_input_is_tied_to_the_full_prior(learned_model, mixed_batch):
    loss = MissingModalityLoss(learned_model, prior_weight=2.0, max_dropped=None)
    assert "loss_mis_prior" in loss.out_keys
    torch.manual_seed(0)
    td = learned_model.train()(loss.prepare(mixed_batch.clone()))
    out = loss.loss_from_outputs(td)
    eligible = torch.stack([td.get(keys.drop_key(n)) for n in NAMES], 1).any(1)
    kl = kl_divergence(
        Normal(td.get(keys.PRIOR_LOC), td.get(keys.PRIOR_SCALE)),
        Normal(td.get(keys.PRIOR_DROPPED_LOC), td.get(keys.PRIOR_DROPPED_SCALE)),
    ).sum(-1)
    torch.testing.assert_close(out["loss_mis_prior"], 2.0 * kl[eligible].mean())
    assert out["loss_mis_prior"] > 0


def test_prior_tie_teacher_is_detached_by_default(learned_model):
    prior = torch.randn(4, 3, requires_grad=True)
    student = torch.randn(4, 3, requires_grad=True)
    loc = torch.randn(4, 5, 2)
    for detach, teacher_has_grad in ((True, False), (False, True)):
        prior.grad = student.grad = None
        td = outputs(loc, loc.clone())
        td.update(
            {
                keys.PRIOR_LOC: prior,
                keys.PRIOR_SCALE: torch.ones(4, 3),
                keys.PRIOR_DROPPED_LOC: student,
                keys.PRIOR_DROPPED_SCALE: torch.ones(4, 3),
            }
        )
        loss = MissingModalityLoss(learned_model, detach_teacher=detach)
        loss.loss_from_outputs(td)["loss_mis_prior"].backward()
        assert (prior.grad is not None) == teacher_has_grad and student.grad is not None


def test_standard_prior_has_no_prior_tie(small_model, batch):
    loss = MissingModalityLoss(small_model, prior_weight=1.0)
    assert "loss_mis_prior" not in loss.out_keys
    assert "loss_mis_prior" not in loss(batch).keys()
