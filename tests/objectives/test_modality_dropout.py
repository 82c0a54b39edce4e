import pytest
import torch

from mmf_rl.objectives import ELBOLoss, LossConfig, ModalityDropout, resolve_observed_dropout
from mmf_rl.objectives.modality_dropout import drop_at_rates, uniform_nonempty_subsets, with_modality_dropout


def test_subsets_are_uniform_over_the_nonempty_subsets_of_the_present_modalities():
    torch.manual_seed(0)
    present = torch.tensor([[True, True, True], [True, False, True]]).repeat(14000, 1)
    kept = uniform_nonempty_subsets(present)
    assert not (kept & ~present).any() and kept.any(1).all()
    for row, count in ((0, 7), (1, 3)):
        patterns = [tuple(p) for p in kept[row::2].tolist()]
        frequencies = [patterns.count(p) / len(patterns) for p in set(patterns)]
        assert len(frequencies) == count
        # 7000 draws: a share's standard error is below 0.005
        assert max(abs(f - 1 / count) for f in frequencies) < 0.02, frequencies


def test_rates_remove_each_modality_at_its_rate_and_never_the_last_one():
    torch.manual_seed(0)
    present = torch.ones(20000, 3, dtype=torch.bool)
    present[::4, 2] = False
    kept = drop_at_rates(present, torch.tensor([0.3, 0.0, 0.9]))
    assert not (kept & ~present).any() and kept.any(1).all()
    assert kept[:, 1].all()  # rate 0
    assert abs(1 - kept[:, 0].float().mean() - 0.3) < 0.02


def test_a_sample_with_one_modality_keeps_it():
    present = torch.tensor([[False, True, False]] * 50)
    assert torch.equal(uniform_nonempty_subsets(present), present)
    assert torch.equal(drop_at_rates(present, torch.tensor([0.9, 0.9, 0.9])), present)


@pytest.mark.parametrize(
    ("settings", "match"),
    [
        ({"modality_dropout": "sometimes"}, "must be null, 'subsets' or 'observed'"),
        ({"modality_dropout": {"image": 1.0}}, r"modality_dropout.image must be a rate in \[0, 1\)"),
        ({"modality_dropout": "subsets", "modality_dropout_prob": 0.0}, r"must be in \(0, 1\]"),
        ({"modality_dropout_prob": 0.3}, "read only with loss.modality_dropout=subsets"),
    ],
)
def test_bad_dropout_settings_are_refused_with_the_fix(settings, match):
    with pytest.raises(ValueError, match=match):
        LossConfig(**settings)


def test_observed_dropout_takes_the_training_splits_absence_rates():
    resolved = resolve_observed_dropout(LossConfig(modality_dropout="observed"), {"image": 0.2, "force": 0.0})
    assert resolved.modality_dropout == {"image": 0.2}
    with pytest.raises(ValueError, match="no modality is ever absent"):
        resolve_observed_dropout(LossConfig(modality_dropout="observed"), {"image": 0.0})
    with pytest.raises(ValueError, match="resolve it with resolve_observed_dropout"):
        with_modality_dropout(object(), LossConfig(modality_dropout="observed"))


def test_rates_naming_an_unknown_modality_are_refused(small_model):
    with pytest.raises(ValueError, match=r"\['camera'\], which are not modalities of the model"):
        ModalityDropout(ELBOLoss(small_model), rates={"camera": 0.1})
