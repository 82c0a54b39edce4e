"""mmf_rl.compare.entries: the catalogue `mmf-rl compare` offers, entry checks, the runs behind a cell."""

from __future__ import annotations

from pathlib import Path

import pytest

from mmf_rl.compare import entries
from mmf_rl.compare.entries import Budget, Entry, Study
from tests.compare.helpers import PAPER_SUBSETS, PUSH_MODALITIES


def study(tmp_path: Path, labels: list[str], retrained_for=None) -> Study:
    return Study(
        out=tmp_path,
        budget=Budget(steps=4, batch_size=8, seeds=(0, 1)),
        entries=tuple(entries.select_entries(entries.CATALOGUE, labels)),
        modalities=tuple(PUSH_MODALITIES),
        retrained_for=retrained_for,
    )


def test_the_catalogue_is_labelled_once_and_names_no_modality():
    labels = [e.label for e in entries.CATALOGUE]
    assert len(labels) == len(set(labels)) and labels[0] == "paper"
    assert set(entries.DEFAULT_ENTRIES) == {"paper", "LF-LSTM", "MVAE", "MulT", "recommended"}
    assert not any("modalities" in o for e in entries.CATALOGUE for o in e.overrides)
    for entry in entries.CATALOGUE:
        if entry.kind == "retrained":
            assert entry.base.kind == "zero-fill" and entry.overrides == entry.base.overrides
        if entry.kind == "learned fusion":  # the same prior with the attention fusion: one change apart
            assert entry.base.kind == "variant" and "model.prior=learned" in entry.base.overrides
            changed = set(entry.overrides) ^ set(entry.base.overrides)
            assert len(changed) == 1 and next(iter(changed)).startswith("model.fusion=")


def test_an_entry_states_its_kind_and_base():
    with pytest.raises(ValueError, match="kind 'baseline' is not one of"):
        Entry("x", "baseline", ())
    with pytest.raises(ValueError, match="a base is given exactly for retrained and learned fusion"):
        Entry("x (retrained)", "retrained", ("model=mult",))


def test_selection_keeps_catalogue_order_and_needs_the_paper_model():
    chosen = entries.select_entries(entries.CATALOGUE, ["MulT", "paper"])
    assert [e.label for e in chosen] == ["paper", "MulT"]
    with pytest.raises(ValueError, match=r"unknown \['Mult'\]"):
        entries.select_entries(entries.CATALOGUE, ["paper", "Mult"])
    with pytest.raises(ValueError, match="'paper' missing"):
        entries.select_entries(entries.CATALOGUE, ["MulT"])
    chosen = entries.select_entries(entries.CATALOGUE, ["MulT"], paper_required=False)
    assert [e.label for e in chosen] == ["MulT"]
    with pytest.raises(ValueError, match=r"entries: unknown \['Mult'\]; the entries are"):
        entries.select_entries(entries.CATALOGUE, ["Mult"], paper_required=False)


def test_a_retrained_entry_reuses_its_base_run_and_trains_one_model_per_subset(tmp_path):
    retrained = next(e for e in entries.CATALOGUE if e.label == "LF-LSTM (retrained)")
    plan = entries.run_plan(retrained, study(tmp_path, ["paper", "LF-LSTM (retrained)"], PAPER_SUBSETS))
    described = [(e.label, seed, run.relative_to(tmp_path).as_posix(), x, s) for e, seed, run, x, s in plan]
    force, proprio = ("+data.missing.force=1.0",), ("+data.missing.proprio=1.0",)
    assert described == [
        ("LF-LSTM", 0, "lf_lstm/seed0", (), "all"),
        ("LF-LSTM (retrained)", 0, "lf_lstm__retrained/without_force/seed0", force, "without_force"),
        ("LF-LSTM (retrained)", 0, "lf_lstm__retrained/without_proprio/seed0", proprio, "without_proprio"),
        ("LF-LSTM", 1, "lf_lstm/seed1", (), "all"),
        ("LF-LSTM (retrained)", 1, "lf_lstm__retrained/without_force/seed1", force, "without_force"),
        ("LF-LSTM (retrained)", 1, "lf_lstm__retrained/without_proprio/seed1", proprio, "without_proprio"),
    ]
    every = entries.run_plan(retrained, study(tmp_path, ["paper", "LF-LSTM (retrained)"]))
    assert len(every) == 2 * (1 + 6)  # every subset but "all"
    assert [run for _, _, run, _, _ in entries.run_plan(entries.PAPER, study(tmp_path, ["paper"]))] == [
        tmp_path / "paper" / "seed0",
        tmp_path / "paper" / "seed1",
    ]


def test_the_recommended_entry_trains_the_preset_the_readme_recommends(tmp_path):
    """``recommended`` is ``experiment=robust_mult``: MulT with modality dropout and L_mis beside its NLL,
    the same training as the catalogue's "MulT, modality dropout + L_mis"."""
    from mmf_rl.compare.runs import compose_train

    s = study(tmp_path, ["paper", "recommended", "MulT, modality dropout + L_mis"])
    preset, spelled_out = (compose_train(e, 0, s, tmp_path / "run") for e in s.entries[1:])
    assert preset.model == spelled_out.model and preset.loss == spelled_out.loss
    assert preset.model.name == "mult" and preset.loss.modality_dropout == "subsets"
    assert list(preset.loss.terms) == ["nll", "mis"] and preset.run_dir == str(tmp_path / "run")
