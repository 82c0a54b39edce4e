"""mmf_rl.compare.collect: what the completed runs wrote, read back per entry."""

from __future__ import annotations

import json

import pytest

from mmf_rl.compare import collect, entries
from mmf_rl.compare.entries import Budget, Study, subsets
from tests.compare.helpers import PAPER_SUBSETS, PUSH_MODALITIES


def test_timing_separates_the_training_loop_from_the_rest_of_a_run():
    runs = {
        "paper": [
            {"step_seconds": 0.05, "seconds": 60.0, "steps": 1000, "batch_size": 32},
            {"step_seconds": 0.07, "seconds": 80.0, "steps": 1000, "batch_size": 32, "jobs": 2},
        ]
    }
    measured = collect.timing(runs)["paper"]
    assert measured["ms_per_step"] == pytest.approx(60.0)
    assert measured["other_seconds"] == pytest.approx(10.0)
    assert measured["runs"] == 2 and measured["batch_size"] == 32
    assert measured["jobs"] == 1.5  # a result written before "jobs" was recorded counts as 1


def test_coverage_and_kl_are_read_per_run_from_the_run_a_cell_comes_from(tmp_path):
    """A retrained entry's cell comes from the run trained for that subset; its "all" cell (and KL)
    from the base's all-modality run."""
    entry = next(e for e in entries.CATALOGUE if e.label == "LF-LSTM (retrained)")
    study = Study(
        tmp_path,
        Budget(4, 8, (0, 1)),
        (entries.PAPER, entry),
        tuple(PUSH_MODALITIES),
        retrained_for=PAPER_SUBSETS,
    )
    plan = entries.run_plan(entry, study)
    for index, (_, seed, run_dir, _, subset) in enumerate(plan):
        value = 0.70 + 0.01 * index  # distinct per run: the cell must come from the right one
        scores = {
            name: {
                "coverage_90": value + (0.5 if name != subset else 0),
                "kl": value,
                "width_90": 10 * value + (5 if name != subset else 0),
            }
            for name, _ in subsets(PUSH_MODALITIES)
        }
        (run_dir / "eval").mkdir(parents=True)
        (run_dir / "eval" / "results.json").write_text(
            json.dumps({"subsets": scores, "scale_calibration": {"split": "val"} if seed == 0 else None})
        )
    cells, recalibrated = collect.entry_coverage(entry, study)
    assert set(cells) == set(PAPER_SUBSETS)
    expected = {s: sum(0.70 + 0.01 * i for i, p in enumerate(plan) if p[4] == s) / 2 for s in cells}
    assert cells == pytest.approx(expected)
    assert not recalibrated  # seed 1's runs kept the scale as trained
    assert collect.entry_kl(entry, study) == pytest.approx(expected["all"])
    widths = collect.entry_metric(entry, study, "width_90")
    assert widths == pytest.approx({s: 10 * v for s, v in expected.items()})
    assert collect.entry_metric(entry, study, "crps") == {}  # runs scored before the CRPS existed


def write_completed(run_dir, test_errors: list[float], train_mse: float | None) -> None:
    result = {"subsets": {"all": {"squared_error": test_errors}}}
    if train_mse is not None:
        result["train_mse"] = train_mse
    (run_dir / "eval").mkdir(parents=True, exist_ok=True)
    (run_dir / "eval" / "window_errors.json").write_text(json.dumps(result))


def test_fit_is_the_mean_over_the_entrys_own_runs_and_absent_for_runs_scored_before_it(tmp_path):
    study = Study(tmp_path, Budget(4, 8, (0, 1)), (entries.PAPER,), tuple(PUSH_MODALITIES))
    (_, _, seed0, _, _), (_, _, seed1, _, _) = entries.run_plan(entries.PAPER, study)
    write_completed(seed0, [0.2, 0.4], train_mse=0.1)
    write_completed(seed1, [0.5], train_mse=None)  # a run completed before train_mse was recorded
    assert collect.entry_fit(entries.PAPER, study) is None
    write_completed(seed1, [0.5], train_mse=0.3)
    assert collect.entry_fit(entries.PAPER, study) == pytest.approx({"train": 0.2, "test": 0.4})


def test_a_retrained_entry_has_no_fit_of_its_own(tmp_path):
    # Its all-sensor cell is its base's run, whose fit the base's own row shows.
    entry = next(e for e in entries.CATALOGUE if e.label == "LF-LSTM (retrained)")
    study = Study(tmp_path, Budget(4, 8, (0,)), (entry,), tuple(PUSH_MODALITIES), retrained_for=PAPER_SUBSETS)
    for _, _, run_dir, _, _ in entries.run_plan(entry, study):
        write_completed(run_dir, [0.5], train_mse=0.3)
    assert collect.entry_fit(entry, study) is None
