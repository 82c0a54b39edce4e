import dataclasses
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch.distributions import Normal, kl_divergence

from mmf_rl import keys
from mmf_rl.cli import main as cli
from mmf_rl.configuration import compose_config, to_container
from mmf_rl.datasets import WindowDataset
from mmf_rl.models import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import CombinedLoss, ELBOLoss, LossConfig, MissingModalityLoss
from tests.conftest import HISTORY, SMALL_MODALITIES, make_batch, push_train_overrides
from tests.reliability.conftest import edit_frames, push_data_config

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


def test_loss_is_positive_with_finite_gradients(small_model, batch):
    small_model.train()
    out = MissingModalityLoss(small_model, weight=2.0)(batch)
    assert out["loss_mis"] > 0 and out["mis_fraction"] == 1
    torch.testing.assert_close(out["loss_mis"], 2.0 * out["mis_kl"])
    out["loss_mis"].backward()
    grads = [p.grad for p in small_model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_teacher_gets_gradient_from_loss_mis_unless_detached(small_model):
    loc = torch.randn(4, 5, 2, requires_grad=True)
    student = torch.randn(4, 5, 2, requires_grad=True)
    # The default trains both sides, as the paper does.
    for kwargs, teacher_has_grad in (
        ({"detach_teacher": True}, False),
        ({"detach_teacher": False}, True),
        ({}, True),
    ):
        loc.grad = None
        loss = MissingModalityLoss(small_model, **kwargs)
        loss.loss_from_outputs(outputs(loc, student))["loss_mis"].backward()
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


def test_prior_tie_teacher_gets_gradient_unless_detached(learned_model):
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


# -- tail cuts: a sensor dying mid-window ---------------------------------------------------------


def with_gaps(td, seed: int = 5):
    """``td`` with ``("present_steps", "force")`` losing some steps (never every one of a window)."""
    steps = torch.rand(td.shape[0], HISTORY, generator=torch.Generator().manual_seed(seed)) > 0.3
    steps[:, 0] = True
    td.set(keys.present_steps_key("force"), steps)
    return td


def drawn_cuts(loss, seed=0):
    """``prepare`` on a mixed batch with partial force windows: the whole drops ``[B, M]``, the cuts
    ``[B, M, H]`` (all False for a modality without one) and the present steps ``[B, M, H]``."""
    td = with_gaps(make_batch(2000, present=THREE_PATTERNS))
    torch.manual_seed(seed)
    loss.prepare(td)
    drop = torch.stack([td.get(keys.drop_key(n)) for n in NAMES], 1)
    cut = torch.stack([td.get(keys.drop_steps_key(n)) for n in NAMES], 1)
    steps = torch.stack(
        [td.get(keys.present_steps_key(n), torch.ones(2000, HISTORY).bool()) for n in NAMES], 1
    )
    present = torch.stack([THREE_PATTERNS[n] for n in NAMES], 1)
    return drop, cut, steps & present.unsqueeze(-1)


def test_a_tail_cut_removes_the_last_present_steps_of_one_modality_and_keeps_one(small_model):
    drop, cut, steps = drawn_cuts(MissingModalityLoss(small_model, max_dropped=None, step_drop_prob=0.5))
    cut_rows = cut.flatten(1).any(1)
    assert not (cut & ~steps).any()  # only present steps are cut
    assert torch.equal(cut.any(-1).sum(1), cut_rows.long())  # of one modality
    assert not (drop[cut_rows]).any()  # instead of the whole drop
    kept = steps & ~cut
    assert bool(kept.any(-1)[cut.any(-1)].all())  # the cut modality keeps a present step
    # The last ones: no step the student keeps comes after a cut step.
    index = torch.arange(HISTORY).expand_as(cut)
    last_kept = torch.where(kept, index, -1).amax(-1)
    first_cut = torch.where(cut, index, HISTORY).amin(-1)
    assert bool((last_kept < first_cut).all())
    # Every sample has a windowed modality with two present steps here: half get a cut, single-modality
    # samples included (rows 2, 4, 7, ...), whose modality stays present.
    assert abs(float(cut_rows.float().mean()) - 0.5) < 0.05
    single = steps.any(-1).sum(1) == 1
    assert bool(cut_rows[single].any()) and bool(kept.any(-1)[single].any(1).all())
    # A full window of H steps loses k uniform in 1..H-1.
    lengths = cut.sum(-1)[cut.any(-1) & steps.all(-1)]
    assert set(lengths.tolist()) == set(range(1, HISTORY))


def test_max_dropped_steps_caps_the_cut_and_the_draw_repeats_under_a_seed(small_model):
    loss = MissingModalityLoss(small_model, step_drop_prob=0.5, max_dropped_steps=1)
    _, cut, _ = drawn_cuts(loss)
    assert set(cut.sum(-1)[cut.any(-1)].tolist()) == {1}
    for first, again in zip(drawn_cuts(loss, seed=3), drawn_cuts(loss, seed=3), strict=True):
        assert torch.equal(first, again)
    assert not torch.equal(drawn_cuts(loss, seed=3)[1], drawn_cuts(loss, seed=4)[1])


def test_a_burst_cut_removes_a_run_of_present_steps_anywhere_and_keeps_one(small_model):
    burst = MissingModalityLoss(small_model, max_dropped=None, step_drop_prob=0.5, step_cut="burst")
    drop, cut, steps = drawn_cuts(burst)
    assert not (cut & ~steps).any() and not drop[cut.flatten(1).any(1)].any()
    kept = steps & ~cut
    assert bool(kept.any(-1)[cut.any(-1)].all())  # the cut modality keeps a present step
    # Consecutive among the present steps: no present step the student keeps lies inside the run.
    index = torch.arange(HISTORY).expand_as(cut)
    first_cut = torch.where(cut, index, HISTORY).amin(-1, keepdim=True)
    last_cut = torch.where(cut, index, -1).amax(-1, keepdim=True)
    assert not (kept & (index > first_cut) & (index < last_cut)).any()
    # Full windows: every run length 1..H-1, runs that end before the window does (gaps the tail cut
    # never makes) and runs that start at its first step.
    full = cut.any(-1) & steps.all(-1)
    assert set(cut.sum(-1)[full].tolist()) == set(range(1, HISTORY))
    assert bool((last_cut.squeeze(-1)[full] < HISTORY - 1).any()) and bool(
        (first_cut.squeeze(-1)[full] == 0).any()
    )
    # The same samples are cut as with tail cuts under the same seed; only where differs.
    tail = MissingModalityLoss(small_model, max_dropped=None, step_drop_prob=0.5)
    assert torch.equal(drawn_cuts(tail)[1].any(-1), cut.any(-1))


@pytest.mark.parametrize("max_dropped", [1, None])
def test_no_tail_cuts_by_default_and_the_same_random_draws_as_the_whole_drop(small_model, max_dropped):
    td = with_gaps(make_batch(64, present={n: p[:64] for n, p in THREE_PATTERNS.items()}))
    loss = MissingModalityLoss(small_model, max_dropped=max_dropped)
    assert loss.step_drop_prob == 0 and "mis_tail_fraction" not in loss.out_keys
    assert not any(k[0] == keys.DROP_STEPS for k in loss.in_keys if isinstance(k, tuple))
    torch.manual_seed(0)
    loss.prepare(td)
    after = torch.rand(3)
    assert keys.DROP_STEPS not in td.keys()
    # The paper's drop draws one score per modality (and, above one dropped, one count) per sample.
    torch.manual_seed(0)
    torch.rand(64, len(NAMES))
    if max_dropped is None:
        torch.rand(64)
    assert torch.equal(after, torch.rand(3))


@pytest.mark.parametrize(
    "option, message",
    [
        ({"step_drop_prob": -0.1}, r"step_drop_prob must be in \[0, 1\]"),
        ({"step_drop_prob": 1.5}, r"step_drop_prob must be in \[0, 1\]"),
        ({"max_dropped_steps": 0}, r"max_dropped_steps must be >= 1 \(or None: up to all but one"),
        ({"step_cut": "middle"}, r"step_cut must be one of \['tail', 'burst'\]"),
    ],
)
def test_bad_tail_cut_options_name_the_argument(small_model, option, message):
    with pytest.raises(ValueError, match=message):
        MissingModalityLoss(small_model, **option)


def test_tail_cuts_need_a_windowed_modality(small_config):
    vectors = dataclasses.replace(small_config, modalities=[keys.ModalitySpec("goal", "vector", (3,))])
    with pytest.raises(ValueError, match="has none; set step_drop_prob=0"):
        MissingModalityLoss(MultimodalForecaster(vectors), step_drop_prob=0.5)


def test_tail_cut_samples_count_and_train_the_student(small_model, batch):
    loss = MissingModalityLoss(small_model, step_drop_prob=1.0)
    assert {keys.drop_steps_key(n) for n in NAMES} <= set(loss.in_keys)
    small_model.train()
    out = loss(batch)
    assert out["mis_tail_fraction"] == 1 and out["mis_fraction"] == 1 and out["loss_mis"] > 0
    out["loss_mis"].backward()
    grads = [p.grad for p in small_model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_tail_cut_options_come_from_the_loss_config():
    overrides = ["loss.step_drop_prob=0.25", "loss.max_dropped_steps=2", "loss.step_cut=burst"]
    loss_cfg = LossConfig.from_dict(to_container(compose_config("train", overrides).loss))
    torch.manual_seed(0)
    model = MultimodalForecaster(
        ForecasterConfig(modalities=list(SMALL_MODALITIES), history=HISTORY, horizon=5, target_dim=2)
    )
    loss = MissingModalityLoss.from_config(model, loss_cfg)
    assert (loss.step_drop_prob, loss.max_dropped_steps, loss.step_cut) == (0.25, 2, "burst")
    assert (LossConfig().step_drop_prob, LossConfig().max_dropped_steps, LossConfig().step_cut) == (
        0.0,
        None,
        "tail",
    )
    with pytest.raises(ValueError, match=r"loss.step_cut must be one of \['tail', 'burst'\], found 'middle'"):
        LossConfig(step_cut="middle")


def camera_dies_mid_episode(frames) -> None:
    """The camera is lost from frame 34 of every episode on: windows over frame 34 hold it for some steps."""
    from mmf_rl.record import CAMERA_VALID_KEY

    frames.loc[frames["frame_index"] >= 34, CAMERA_VALID_KEY] = False


def test_training_with_tail_cuts_on_partial_windows_of_recorded_push_data(recorded_push_root, tmp_path):
    root = Path(shutil.copytree(recorded_push_root, tmp_path / "push"))
    edit_frames(root, camera_dies_mid_episode)
    run = tmp_path / "run"
    overrides = push_train_overrides(root, tmp_path / "cache", run, steps=4)
    assert cli(["train", *overrides, "data.partial_windows=true", "loss.step_drop_prob=0.5"]) == 0
    scalars = run / "logs" / "scalars" / "train"
    values = {
        name: torch.tensor(
            [float(row.split(",")[-1]) for row in (scalars / f"{name}.csv").read_text().splitlines()]
        )
        for name in ("loss", "loss_mis", "mis_tail_fraction")
    }
    assert all(len(v) and torch.isfinite(v).all() for v in values.values())
    assert bool((values["mis_tail_fraction"] > 0).all())
    dataset = WindowDataset(push_data_config(root, tmp_path / "cache", partial_windows=True))
    batch = dataset.batch(torch.arange(len(dataset)))
    steps, present = batch.get(keys.present_steps_key("image")), batch.get(keys.present_key("image"))
    assert bool((present & ~steps.all(1)).any()), "some windows hold the camera for some steps only"
