"""Missing-sensor training for every registered model: L_mis's student pass and modality dropout honour
presence the same way in every model (a mixed batch = per sample; absent values never read)."""

import pytest
import torch

from mmf_rl import keys
from mmf_rl.models import build_loss
from mmf_rl.objectives import LossConfig, ModalityDropout
from tests.conftest import (
    SMALL_MODALITIES,
    assert_a_few_steps_reduce_the_loss,
    make_batch,
    presence_patterns,
    small_registered_model,
)

NAMES = [s.name for s in SMALL_MODALITIES]
GAUSSIAN_MODELS = ["forecaster", "lf_lstm", "mvae", "mult"]
OWN_TERMS = {
    "forecaster": ["elbo", "mis"],
    "lf_lstm": ["nll", "mis"],
    "mvae": ["elbo", "mis"],
    "mult": ["nll", "mis"],
}
DROPPED = (keys.FORECAST_DROPPED_LOC, keys.FORECAST_DROPPED_SCALE)


def drops_of_every_pattern() -> "tuple":
    """A batch with one sample per (present pattern, dropped proper subset of it) pair."""
    rows = [
        (present, dropped)
        for present in presence_patterns(NAMES)
        for dropped in presence_patterns(list(present))
        if len(dropped) < len(present)
    ]
    batch = make_batch(len(rows), present={n: torch.tensor([n in p for p, _ in rows]) for n in NAMES}, seed=4)
    for name in NAMES:
        batch.set(keys.drop_key(name), torch.tensor([name in d for _, d in rows]))
    return batch, rows


def without_dropped(batch):
    """The batch with each sample's dropped modalities absent and no drop masks: what the student sees."""
    student = batch.clone()
    for name in NAMES:
        student.set(
            keys.present_key(name), batch.get(keys.present_key(name)) & ~batch.get(keys.drop_key(name))
        )
        del student[keys.drop_key(name)]
    return student


@pytest.mark.parametrize("name", GAUSSIAN_MODELS)
def test_student_forecast_is_the_forecast_without_the_dropped_modalities(name):
    """Per sample, in one pass: the student's forecast equals the model's forecast with the dropped
    modalities absent (the paper model's student reads the teacher's z, here z = 0 in eval)."""
    model = small_registered_model(name)
    batch, _ = drops_of_every_pattern()
    with torch.no_grad():
        out = model(batch.clone())
        alone = model(without_dropped(batch))
    for dropped_key, key in zip(DROPPED, (keys.FORECAST_LOC, keys.FORECAST_SCALE), strict=True):
        torch.testing.assert_close(out.get(dropped_key), alone.get(key), rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", GAUSSIAN_MODELS)
def test_values_under_dropped_modalities_do_not_reach_the_student(name):
    model = small_registered_model(name)
    batch, _ = drops_of_every_pattern()
    garbage = batch.clone()
    g = torch.Generator().manual_seed(5)
    for spec in SMALL_MODALITIES:
        gone = batch.get(keys.drop_key(spec.name)) | ~batch.get(spec.present_key)
        obs = garbage.get(spec.obs_key)
        junk = (
            torch.randint(1, 256, obs.shape, generator=g, dtype=torch.uint8)
            if spec.kind == "image"
            else 1e6 * torch.randn(obs.shape, generator=g)
        )
        obs[gone] = junk[gone]
    with torch.no_grad():
        reference, out = model(batch.clone()), model(garbage)
    for key in DROPPED:
        torch.testing.assert_close(out.get(key), reference.get(key), rtol=0, atol=0)


@pytest.mark.parametrize("name", GAUSSIAN_MODELS)
def test_a_drop_that_empties_a_sample_is_refused(name):
    model = small_registered_model(name)
    batch = make_batch(2)
    for spec in SMALL_MODALITIES:
        batch.set(keys.drop_key(spec.name), torch.tensor([True, False]))
    with pytest.raises(ValueError, match="every present modality"):
        model(batch)


@pytest.mark.parametrize("name", ["lf_lstm", "mvae", "mult"])
def test_a_baseline_refuses_step_cuts_with_the_fix(name):
    model = small_registered_model(name)
    batch = make_batch(2)
    for spec in SMALL_MODALITIES:
        batch.set(keys.drop_key(spec.name), torch.zeros(2, dtype=torch.bool))
    windowed = next(s for s in SMALL_MODALITIES if s.kind != "vector")
    batch.set(
        keys.drop_steps_key(windowed.name), torch.zeros(2, batch.get(windowed.obs_key).shape[1], dtype=bool)
    )
    with pytest.raises(ValueError, match="loss.step_drop_prob=0"):
        model(batch)


@pytest.mark.parametrize("dropout", [None, "subsets"])
@pytest.mark.parametrize("name", GAUSSIAN_MODELS)
def test_every_model_trains_with_l_mis_and_modality_dropout(name, dropout):
    """The model's own terms plus L_mis (and dropout) give a finite L_mis and train."""
    model = small_registered_model(name).train()
    loss = build_loss(name, model, LossConfig(terms=OWN_TERMS[name], modality_dropout=dropout))
    out = loss(make_batch(8))
    # Without dropout every sample has 3 modalities, one to drop; a sample the dropout left one has none.
    assert torch.isfinite(out["loss_mis"]) and 0 < float(out["mis_fraction"]) <= 1.0
    assert dropout is not None or float(out["mis_fraction"]) == 1.0
    assert ("dropout_fraction" in out.keys()) == (dropout is not None)
    assert_a_few_steps_reduce_the_loss(model, loss)


@pytest.mark.parametrize("name", GAUSSIAN_MODELS)
def test_modality_dropout_reaches_the_supervised_term(name):
    """The supervised term of a dropped batch equals the term of the same batch with those modalities
    absent, for the same draw."""
    model = small_registered_model(name)  # eval: no latent noise
    loss = build_loss(name, model, LossConfig(terms=[OWN_TERMS[name][0]], modality_dropout="subsets"))
    assert isinstance(loss, ModalityDropout)
    batch = make_batch(16)
    torch.manual_seed(7)
    dropped = loss.prepare(batch.clone())
    assert not all(bool(dropped.get(keys.present_key(n)).all()) for n in NAMES)
    torch.manual_seed(7)
    with torch.no_grad():
        out = loss(batch)
        plain = loss.loss(dropped)
    torch.testing.assert_close(out["loss_nll"], plain["loss_nll"])
