"""benchmarks/accuracy.py: the paired bootstrap over test episodes, "best or tied", the summary line."""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from tests.conftest import load_benchmark

accuracy = load_benchmark("accuracy")
SUBSETS = [
    "all",
    "without_force",
    "without_image",
    "without_proprio",
    "only_force",
    "only_image",
    "only_proprio",
]


def windows(num_episodes: int = 8, per_episode: int = 5, seed: int = 0, scale: float = 1.0):
    """(episode of each window, squared errors) with episode-dependent levels, as a test split gives."""
    g = torch.Generator().manual_seed(seed)
    episodes = [e for e in range(num_episodes) for _ in range(per_episode)]
    level = torch.rand(num_episodes, generator=g)[torch.tensor(episodes)]
    return episodes, (scale * level * (1 + 0.1 * torch.rand(len(episodes), generator=g))).tolist()


def cell(mean: float, low: float, high: float) -> accuracy.Cell:
    return accuracy.Cell(mean, low, high, [mean], 10, torch.full((4,), mean))


def test_episode_totals_sum_per_episode_in_the_given_order():
    sums, counts = accuracy.episode_totals([3, 1, 3, 3], [1.0, 2.0, 3.0, 4.0], order=[1, 3, 5])
    assert sums.tolist() == [2.0, 8.0, 0.0]
    assert counts.tolist() == [1.0, 3.0, 0.0]
    with pytest.raises(ValueError, match=r"episodes \[7\]"):
        accuracy.episode_totals([7], [1.0], order=[1, 3])


def test_bootstrap_weights_resample_episodes_with_replacement_from_one_seed():
    weights = accuracy.bootstrap_weights(6, resamples=50, seed=3)
    assert weights.shape == (50, 6)
    assert torch.all(weights.sum(1) == 6)
    assert torch.equal(weights, accuracy.bootstrap_weights(6, resamples=50, seed=3))
    assert not torch.equal(weights, accuracy.bootstrap_weights(6, resamples=50, seed=4))
    assert (weights == 0).any() and (weights > 1).any()  # some episodes left out, some drawn twice


def test_cell_mean_is_the_seed_mean_of_window_means_and_the_interval_holds_it():
    order = list(range(8))
    weights = accuracy.bootstrap_weights(8, resamples=500)
    seeds = [windows(seed=s) for s in (0, 1, 2)]
    c = accuracy.bootstrap_cell([accuracy.episode_totals(e, err, order) for e, err in seeds], weights)
    expected = sum(sum(err) / len(err) for _, err in seeds) / 3
    assert c.mean == pytest.approx(expected)
    assert c.per_seed == pytest.approx([sum(err) / len(err) for _, err in seeds])
    assert c.windows == 40
    assert c.low < c.mean < c.high
    # Episode-level variation dominates, so the interval is far wider than the within-episode noise.
    assert c.high - c.low > 0.05


def test_constant_errors_give_a_zero_width_interval():
    episodes = [e for e in range(5) for _ in range(3)]
    c = accuracy.bootstrap_cell(
        [accuracy.episode_totals(episodes, [0.3] * 15, range(5))],
        accuracy.bootstrap_weights(5, resamples=100),
    )
    assert c.low == pytest.approx(0.3) and c.high == pytest.approx(0.3)


def test_the_bootstrap_is_paired_across_entries():
    """An entry that is worse by exactly 0.01 on every window is worse by 0.01 on every resample:
    the paired difference interval is a point, although both marginal intervals are wide."""
    order = list(range(8))
    weights = accuracy.bootstrap_weights(8, resamples=300)
    episodes, errors = windows()
    a = accuracy.bootstrap_cell([accuracy.episode_totals(episodes, errors, order)], weights)
    b = accuracy.bootstrap_cell(
        [accuracy.episode_totals(episodes, [x + 0.01 for x in errors], order)], weights
    )
    assert accuracy.overlap(a, b)
    low, high = accuracy.difference_interval(b, a)
    assert low == pytest.approx(0.01) and high == pytest.approx(0.01)


def test_seeds_scored_on_different_windows_are_refused():
    weights = accuracy.bootstrap_weights(2, resamples=10)
    with pytest.raises(ValueError, match="different test windows"):
        accuracy.bootstrap_cell(
            [
                accuracy.episode_totals([0, 1], [1.0, 1.0], [0, 1]),
                accuracy.episode_totals([0], [1.0], [0, 1]),
            ],
            weights,
        )


def test_best_or_tied_is_decided_by_overlapping_intervals():
    cells = {"paper": cell(0.30, 0.27, 0.33), "rival": cell(0.28, 0.25, 0.31), "far": cell(0.5, 0.45, 0.55)}
    assert accuracy.best_or_tied(cells, "paper")  # worse mean, intervals overlap: tied
    assert not accuracy.best_or_tied(cells, "far")
    assert accuracy.best_or_tied(cells, "rival")
    cells["rival"] = cell(0.20, 0.18, 0.22)
    assert not accuracy.best_or_tied(cells, "paper")


def test_paper_subsets_lead_the_table():
    assert accuracy.ordered_subsets(SUBSETS) == [
        "all",
        "without_proprio",
        "without_force",
        "without_image",
        "only_force",
        "only_image",
        "only_proprio",
    ]
    assert accuracy.subset_title("without_proprio") == "image+force (without_proprio)"
    assert accuracy.subset_title("all") == "image+force+proprio"


def make_table(paper: float, zero_fill: float, retrained: float, fusion: float | None) -> accuracy.Table:
    table = accuracy.Table(subsets=accuracy.ordered_subsets(SUBSETS))
    rows = {
        "paper": ("paper", paper),
        "LF-LSTM": ("zero-fill", zero_fill),
        "LF-LSTM (retrained)": ("retrained", retrained),
    }
    if fusion is not None:
        rows["paper fusion=sum"] = ("fusion", fusion)
    for label, (kind, level) in rows.items():
        table.kinds[label] = kind
        table.cells[label] = {
            s: cell(level * (1 + 0.1 * i), level * (1 + 0.1 * i) - 0.01, level * (1 + 0.1 * i) + 0.01)
            for i, s in enumerate(table.subsets)
        }
    return table


def test_summary_line_has_the_issues_format():
    line, summary = accuracy.summarize(make_table(paper=0.30, zero_fill=0.305, retrained=0.2, fusion=0.36))
    pattern = (
        r"summary: paper model best or tied in (\d+)/(\d+) subsets \(zero-fill baselines\), (\d+)/3 paper "
        r"subsets vs retrained; fusion spread (\d+)%; mean degradation paper (-?\d+)%, best baseline (-?\d+)%"
    )
    match = re.fullmatch(pattern, line)
    assert match, line
    assert match.groups()[:4] == ("7", "7", "0", "20")
    assert (
        summary["best_or_tied_vs_zero_fill"] == 7 and summary["paper_subsets_best_or_tied_vs_retrained"] == 0
    )
    # Each row degrades by 10% a subset step; the mean over the six subsets is 35% for every entry.
    assert match.group(5) == "35" and match.group(6) == "35"


def test_summary_line_says_what_the_run_lacks():
    table = make_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=None)
    del table.kinds["LF-LSTM (retrained)"], table.cells["LF-LSTM (retrained)"]
    line, summary = accuracy.summarize(table)
    assert (
        "in 7/7 subsets" in line and "-/3 paper subsets vs retrained" in line and "fusion spread -;" in line
    )
    assert summary["fusion_spread"] is None


def test_projection_scales_the_measured_step_time():
    budget = accuracy.Budget(
        image_size=32,
        batch_size=32,
        steps=1000,
        seeds=(0, 1, 2),
        episodes=200,
        entries=("paper", "LF-LSTM", "LF-LSTM (retrained)"),
    )
    measured = {
        "paper": {"ms_per_step": 50.0, "other_seconds": 4.0, "runs": 1, "batch_size": 32},
        "LF-LSTM": {"ms_per_step": 100.0, "other_seconds": 6.0, "runs": 1, "batch_size": 32},
    }
    seconds, missing = accuracy.projection(measured, budget)
    # paper 3 x (50 + 4) + LF-LSTM 3 x (100 + 6) + retrained (from LF-LSTM's time) 6 subsets x 3 x 106 s
    assert seconds == pytest.approx(3 * 54 + 3 * 106 + 18 * 106)
    assert missing == []
    seconds, missing = accuracy.projection({"paper": measured["paper"]}, budget)
    assert missing == ["LF-LSTM", "LF-LSTM (retrained)"]


def test_entries_are_labelled_once_and_name_the_base_they_are_compared_with():
    labels = [e.label for e in accuracy.ENTRIES]
    assert len(labels) == len(set(labels)) and labels[0] == "paper"
    entries = {e.label: e for e in accuracy.ENTRIES}
    for entry in accuracy.ENTRIES:
        assert entry.kind in (
            "paper",
            "variant",
            "zero-fill",
            "retrained",
            "fusion",
            "learned fusion",
            "ablation",
        )
        assert (entry.base is not None) == (entry.kind in ("retrained", "learned fusion"))
        if entry.kind == "retrained":
            assert entries[entry.base].kind == "zero-fill"
        if entry.kind == "learned fusion":  # the same prior with the attention fusion: one change apart
            base = entries[entry.base]
            assert base.kind == "variant" and "model.prior=learned" in base.overrides
            changed = set(entry.overrides) ^ set(base.overrides)
            assert len(changed) == 1 and next(iter(changed)).startswith("model.fusion=")
    for mode in accuracy.MODES.values():
        assert mode.entries is None or set(mode.entries) <= set(labels)


def test_timing_separates_the_training_loop_from_the_rest_of_a_run():
    runs = {
        "paper": [
            {"step_seconds": 0.05, "seconds": 60.0, "steps": 1000, "batch_size": 32},
            {"step_seconds": 0.07, "seconds": 80.0, "steps": 1000, "batch_size": 32},
        ]
    }
    measured = accuracy.timing(runs)["paper"]
    assert measured["ms_per_step"] == pytest.approx(60.0)
    assert measured["other_seconds"] == pytest.approx(10.0)
    assert measured["runs"] == 2 and measured["batch_size"] == 32


def test_training_rate_is_the_last_logged_throughput(tmp_path):
    path = tmp_path / "logs" / "scalars" / "train" / "samples_per_s.csv"
    path.parent.mkdir(parents=True)
    path.write_text("25,410.5\n50,402.25\n")
    assert accuracy.training_rate(tmp_path) == 402.25


def test_best_baseline_degradation_ignores_rows_without_every_subset():
    table = make_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=None)
    for s in table.subsets[1:]:
        table.cells["LF-LSTM (retrained)"][s] = cell(0.2, 0.19, 0.21)  # 0% degradation...
    for s in table.subsets[3:]:
        del table.cells["LF-LSTM (retrained)"][s]  # ...but only on the paper's subsets
    line, summary = accuracy.summarize(table)
    assert summary["best_baseline_mean_degradation"] == pytest.approx(0.35)
    assert "0/3 paper subsets vs retrained" in line and line.endswith("best baseline 35%")


def test_window_errors_average_to_the_evaluations_mse_on_recorded_push_data(recorded_push_root, tmp_path):
    """The benchmark's own pass over the test windows (per-window errors, with their episodes) scores
    the same windows the same way as `mmf-rl eval`, on data recorded by the project's recorder."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.datasets import DataConfig, WindowDataset
    from mmf_rl.eval.eval_command import run_evaluation
    from mmf_rl.trainers.train_command import train
    from tests.conftest import push_train_overrides

    run = tmp_path / "run"
    train(compose_config("train", push_train_overrides(recorded_push_root, tmp_path / "cache", run)))
    summary = run_evaluation(compose_config("eval", [f"checkpoint={run}", "plots=false", "num_samples=0"]))
    errors = accuracy.window_errors(run, "cpu", batch_size=7)  # batches that do not divide the split
    assert set(errors) == set(summary["subsets"])
    data = WindowDataset(DataConfig.from_dict(trained_data_config(run)))
    test_episodes = set(data.split_episodes["test"])
    for name, rows in errors.items():
        metrics = summary["subsets"][name]
        assert len(rows["squared_error"]) == metrics["windows"]
        mean = sum(rows["squared_error"]) / len(rows["squared_error"])
        assert mean == pytest.approx(metrics["mse"], rel=1e-5)
        assert set(rows["episode"]) <= test_episodes
        assert rows["episode"] == data.window_episode[torch.tensor(rows["window"])].tolist()


def trained_data_config(run: Path) -> dict:
    from mmf_rl.checkpoint import load_checkpoint

    return load_checkpoint(run / "checkpoints", with_trainer_state=False).meta["config"]["data"]


def test_projection_counts_runs_measured_side_by_side_once():
    budget = accuracy.Budget(
        image_size=32, batch_size=32, steps=1000, seeds=(0, 1, 2), episodes=200, entries=("paper",)
    )
    alone = {"paper": {"ms_per_step": 50.0, "other_seconds": 4.0, "runs": 3, "batch_size": 32, "jobs": 1}}
    paired = {"paper": {**alone["paper"], "jobs": 2}}
    assert accuracy.projection(paired, budget)[0] == pytest.approx(accuracy.projection(alone, budget)[0] / 2)
    results = [
        {"step_seconds": 0.05, "seconds": 54.0, "steps": 1000, "batch_size": 32, "jobs": 2},
        {"step_seconds": 0.05, "seconds": 54.0, "steps": 1000, "batch_size": 32},  # written before "jobs"
    ]
    assert accuracy.timing({"paper": results})["paper"]["jobs"] == 1.5


def test_learned_prior_fusions_are_compared_with_the_learned_prior_not_the_default_model():
    table = make_table(paper=0.30, zero_fill=0.5, retrained=0.2, fusion=0.30)
    learned = "paper prior=learned"
    rival = f"{learned}, fusion=sum"
    for label, kind, level in ((learned, "variant", 0.40), (rival, "learned fusion", 0.60)):
        table.kinds[label] = kind
        table.cells[label] = {s: cell(level, level - 0.01, level + 0.01) for s in table.subsets}
    differences = accuracy.paired_comparisons(table)["all"]
    assert differences[rival]["reference"] == learned
    assert differences[rival]["difference"] == pytest.approx(-0.20)
    assert differences["paper fusion=sum"]["reference"] == "paper"
    verdicts = accuracy.fusion_verdicts(table, differences)
    # The default prior's sum fusion ties attention; the learned prior's is 0.2 behind it.
    assert verdicts.count("beyond the interval: no") == 1 and verdicts.count("beyond the interval: yes") == 1
    assert f"Paired difference {learned} - fusion ablation" in verdicts


def test_entries_are_checked_against_the_configs_before_any_training(tmp_path):
    args = SimpleNamespace(data=tmp_path / "data", out=tmp_path / "out", device="cpu")
    budget = accuracy.STANDARD
    # The options of issue #13's model variants land with the model changes; every other entry composes here.
    accuracy.check_entries([e for e in accuracy.ENTRIES if e.kind != "variant"], budget, args)
    bogus = accuracy.Entry("paper typo", "variant", ("model=forecaster", "model.fusoin=sum"))
    with pytest.raises(SystemExit, match=r"'paper typo' \(model=forecaster model.fusoin=sum\)"):
        accuracy.check_entries([accuracy.ENTRIES[0], bogus], budget, args)


def test_coverage_is_read_per_run_and_judged_against_the_issues_band(tmp_path):
    """Coverage comes from each run's own evaluation; a retrained entry's cell from the run trained
    for that subset; the table counts the subsets inside 0.80-0.97 and says how the scale was set."""
    import json

    budget = accuracy.Budget(
        image_size=32,
        batch_size=8,
        steps=4,
        seeds=(0, 1),
        episodes=16,
        entries=None,
        retrained_subsets="paper",
    )
    entry = next(e for e in accuracy.ENTRIES if e.label == "LF-LSTM (retrained)")
    plan = accuracy.run_plan(entry, budget, tmp_path)
    for index, (_, seed, run_dir, _, subset) in enumerate(plan):
        value = 0.70 + 0.01 * index  # distinct per run: the cell must come from the right one
        scores = {
            name: {"coverage_90": value + (0.5 if name != subset else 0)} for name, _ in accuracy.subsets()
        }
        (run_dir / "eval").mkdir(parents=True)
        (run_dir / "eval" / "results.json").write_text(
            json.dumps({"subsets": scores, "scale_calibration": {"split": "val"} if seed == 0 else None})
        )
    cells, recalibrated = accuracy.entry_coverage(entry, budget, tmp_path)
    assert set(cells) == {"all", *(name for name in accuracy.PAPER_SUBSETS if name != "all")}
    expected = {
        s: sum(0.70 + 0.01 * i for i, p in enumerate(plan) if p[4] == s) / len(budget.seeds) for s in cells
    }
    assert cells == pytest.approx(expected)
    assert not recalibrated  # seed 1's runs kept the scale as trained
    text = accuracy.coverage_table(
        {"paper": ({"all": 0.85, "only_image": 0.75}, True)}, ["all", "only_image"]
    )
    assert text.splitlines()[-1] == "| paper | 0.850 | 0.750 | 1/2 | recalibrated on val |"
