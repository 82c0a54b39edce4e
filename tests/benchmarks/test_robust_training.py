"""benchmarks/robust_training.py: the architecture x training grid, the recommendation chosen on val, and
a tiny run on the push data recorded by the fixtures."""

from __future__ import annotations

import json
import re
import runpy
from pathlib import Path

import pytest

from mmf_rl.compare.entries import Budget, Study
from mmf_rl.compare.runs import compose_train
from tests.benchmarks.conftest import study_out
from tests.conftest import run_bench

SCRIPT = runpy.run_path(str(Path(__file__).parents[2] / "benchmarks" / "robust_training.py"))
SUMMARY = re.compile(
    r"summary: recommended \(val\) (.+); test best or tied in (\d)/7 subsets against every cell "
    r"\(paired: beaten in \d\); all sensors \d\.\d{3} \(best cell .+ \d\.\d{3}\); mean degradation -?\d+%"
)


@pytest.mark.parametrize("cells", [SCRIPT["PUSH"], SCRIPT["HUMANOID_GRID"]], ids=["push", "humanoid"])
def test_the_grid_is_every_architecture_under_every_training(cells, tmp_path):
    assert len(cells) == 16 and len({e.label for e in cells}) == 16
    kinds = {e.label: e.kind for e in cells}
    assert kinds["paper"] == "paper" and kinds["MulT; complete windows"] == "zero-fill"
    assert kinds["MulT; modality dropout + L_mis"] == kinds["LF-LSTM; L_mis"] == "trained for missing"
    study = Study(tmp_path, Budget(10, 4, (0,)), tuple(cells), ("force", "image", "proprio"))
    for entry in cells:
        if "action" in str(entry.overrides):  # the humanoid's cells need its recording to compose
            continue
        cfg = compose_train(entry, 0, study, tmp_path / "run")
        training = SCRIPT["architecture_and_training"](entry.label)[1]
        assert (cfg.loss.modality_dropout == "subsets") == ("modality dropout" in training), entry.label
        paper_like = cfg.model.name == "forecaster"
        has_mis = cfg.loss.missing_modality_weight > 0 and (paper_like or cfg.loss.terms == ["nll", "mis"])
        assert has_mis == ("L_mis" in training), entry.label


def test_the_recommendation_is_the_cell_closest_to_the_best_in_its_worst_subset():
    val = {
        "a": {"all": 0.30, "only_x": 0.90},  # best with everything, 1.5x the best alone
        "b": {"all": 0.33, "only_x": 0.60},  # 1.1x the best with everything, best alone
        "c": {"all": 0.40, "only_x": 0.62},
    }
    pick, ratio = SCRIPT["recommended"](val)
    assert pick == "b" and ratio == pytest.approx(1.1)


def test_a_tiny_run_writes_the_grid_the_val_choice_and_the_summary_line(
    recorded_push_root, push_cache_dir, tmp_path
):
    out = study_out(tmp_path, push_cache_dir)
    run = run_bench(
        "robust_training", "--tiny", "--data", str(recorded_push_root), "--out", str(out), cwd=tmp_path
    )
    assert run.returncode == 0, run.stderr[-3000:]
    line = run.stdout.strip().splitlines()[-1]
    assert SUMMARY.fullmatch(line), line
    text = (out / "results.md").read_text()
    assert "| architecture | complete windows | modality dropout | L_mis | modality dropout + L_mis |" in text
    assert "| *protocol* | paper | trained for missing |" in text
    assert "## The pick against every cell (test, paired)" in text
    results = json.loads((out / "results.json").read_text())
    assert sorted(results["val"]) == ["MulT; modality dropout + L_mis", "paper"]
    assert results["summary"]["recommended"] in results["val"]
    kept = sorted(out.glob("*/seed0/eval/val_mse.json"))  # each run keeps its val scores
    assert len(kept) == 2 and all(len(json.loads(path.read_text())) == 7 for path in kept)
