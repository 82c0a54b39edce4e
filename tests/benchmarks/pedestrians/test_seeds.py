"""Scores over training seeds: the mean and range arithmetic on hand-made per-seed scores, and
``bench ethucy --seeds`` running each seed into ``<out>/seed<N>`` (the per-seed run faked: nothing
trains) and summing them up."""

from __future__ import annotations

import json

import pytest

from benchmarks import ethucy as bench
from benchmarks.pedestrians import seeds
from benchmarks.pedestrians.recipe import CV, CV_NOISE, PAPER, QUICK, TRAINED
from benchmarks.pedestrians.scoring import METRICS, MODES, average_over_scenes, summary_line


def _scores(value: float, fde: float | None = None) -> dict:
    """Every mode and metric ``value``; the FDEs ``fde`` (default twice ``value``)."""
    fde = 2 * value if fde is None else fde
    metrics = {"ade": value, "fde": fde, "min_ade_k": value, "min_fde_k": fde}
    return {mode: dict(metrics) | {"windows": 9.0} for mode in MODES}


def test_over_seeds_gives_the_mean_and_the_range_per_model_mode_and_metric():
    per_seed = {
        0: {PAPER: _scores(0.20), CV: _scores(0.5), "only seed 0": _scores(1.0)},
        1: {PAPER: _scores(0.26), CV: _scores(0.5)},
        2: {PAPER: _scores(0.23), CV: _scores(0.5)},
    }
    stats = seeds.over_seeds(per_seed)
    assert list(stats) == [PAPER, CV]  # a model missing from a seed is left out
    paper = stats[PAPER]["without_scene"]
    assert paper["min_ade_k"] == pytest.approx({"mean": 0.23, "min": 0.20, "max": 0.26, "range": 0.06})
    assert paper["min_fde_k"] == pytest.approx({"mean": 0.46, "min": 0.40, "max": 0.52, "range": 0.12})
    assert set(paper) == set(METRICS)
    assert stats[CV]["all"]["ade"]["range"] == 0.0
    assert seeds.statistic(stats, "range")[PAPER]["all"]["fde"] == pytest.approx(0.12)


def test_the_average_over_scenes_spread_is_that_of_the_per_seed_averages():
    """Seed 0 good on eth, bad on hotel; seed 1 the other way round: each scene spreads by 0.2, their
    per-seed averages are equal, so the average's range is 0, not the mean of the scenes' ranges."""
    per_seed = {
        0: {"eth": {PAPER: _scores(0.1)}, "hotel": {PAPER: _scores(0.3)}},
        1: {"eth": {PAPER: _scores(0.3)}, "hotel": {PAPER: _scores(0.1)}},
    }
    scenes = seeds.per_scene_over_seeds(per_seed)
    assert scenes["eth"][PAPER]["all"]["min_ade_k"]["range"] == pytest.approx(0.2)
    assert scenes["hotel"][PAPER]["all"]["min_ade_k"]["mean"] == pytest.approx(0.2)
    average = seeds.over_seeds({seed: average_over_scenes(scores) for seed, scores in per_seed.items()})
    assert average[PAPER]["all"]["min_ade_k"] == pytest.approx(
        {"mean": 0.2, "min": 0.2, "max": 0.2, "range": 0.0}
    )


def test_the_seeds_table_prints_each_mean_with_its_range():
    stats = seeds.over_seeds({0: {PAPER: _scores(0.20)}, 1: {PAPER: _scores(0.26)}})
    table = seeds.seeds_table(stats)
    assert table.splitlines()[2].startswith("| paper model | 0.23/0.46 (0.06/0.12) | 0.23/0.46 (0.06/0.12) |")


def test_the_summary_over_seeds_adds_the_spread_and_the_seeds_and_one_seed_s_is_unchanged():
    average = {label: _scores(0.5) for label in [*TRAINED, CV, CV_NOISE]}
    average[PAPER] = _scores(0.25, 0.43)
    average["MulT"] = _scores(0.4, 0.8)
    baselines = ["LF-LSTM", "MulT", CV, CV_NOISE]
    assert summary_line(average, PAPER, CV, baselines, "RUN") == (
        "summary: paper model minADE20/minFDE20 avg 0.25/0.43 (without scene 0.25/0.43, without neighbours "
        "0.25/0.43); constant velocity 0.50/1.00; best baseline MulT 0.40/0.80 (RUN)"
    )
    spread = {label: _scores(0.01, 0.03) for label in average}
    assert summary_line(average, PAPER, CV, baselines, "RUN", spread, [0, 1, 2]) == (
        "summary: paper model minADE20/minFDE20 avg 0.25/0.43 ±0.01/0.03 over seeds 0,1,2 (without scene "
        "0.25/0.43 ±0.01/0.03, without neighbours 0.25/0.43 ±0.01/0.03); constant velocity 0.50/1.00; "
        "best baseline MulT 0.40/0.80 ±0.01/0.03 (RUN)"
    )


def _seed_results(paper: float) -> dict:
    """A quick run's results as ``run_seed`` returns them: trained rows on eth, constant velocity on
    eth and univ."""
    eth = {label: {"scores": _scores(0.5)} for label in [*TRAINED, CV, CV_NOISE]}
    eth[PAPER] = {"scores": _scores(paper)}
    univ = {label: {"scores": _scores(0.6)} for label in (CV, CV_NOISE)}
    averages = {
        "Average over the trained folds (eth)": {m: r["scores"] for m, r in eth.items()},
        "Constant velocity, average over the 5 scenes": {CV: _scores(0.55), CV_NOISE: _scores(0.55)},
    }
    return {"folds": {"eth": eth, "univ": univ}, "averages": averages}


def test_seeds_runs_the_benchmark_once_per_seed_into_its_directory_and_sums_them_up(
    tmp_path, monkeypatch, capsys
):
    ran = []

    def run_seed(args):
        ran.append((args.seed, args.out, args.seeds))
        return _seed_results(0.2 + args.seed / 100), f"summary of seed {args.seed}"

    monkeypatch.setattr(bench, "run_seed", run_seed)
    out = tmp_path / "out"
    assert bench.main(["--quick", "--seeds", "0", "1", "2", "--out", str(out), "--data", str(tmp_path)]) == 0
    assert ran == [(seed, out / f"seed{seed}", None) for seed in (0, 1, 2)]
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert summary == (
        "summary: paper model minADE20/minFDE20 avg 0.21/0.42 ±0.02/0.04 over seeds 0,1,2 (without scene "
        "0.21/0.42 ±0.02/0.04, without neighbours 0.21/0.42 ±0.02/0.04); constant velocity 0.50/1.00; "
        f"best baseline LF-LSTM 0.50/1.00 ±0.00/0.00 ({QUICK.name}; window set trajectron; probe, seen "
        "test: augment=lerobot, augment.rotation=180, sampler=5/5 given by hand; "
        "± range: max - min over the seeds)"
    )
    results = json.loads((out / "results.json").read_text())
    assert results["seeds"] == [0, 1, 2]
    assert results["summaries"] == {str(s): f"summary of seed {s}" for s in (0, 1, 2)}
    assert results["summary"] == summary
    assert results["folds"]["eth"][PAPER]["all"]["min_ade_k"] == pytest.approx(
        {"mean": 0.21, "min": 0.2, "max": 0.22, "range": 0.02}
    )
    assert list(results["folds"]["univ"]) == [CV, CV_NOISE]
    assert list(results["averages"]) == list(_seed_results(0.2)["averages"])
    page = (out / "results.md").read_text()
    assert "## eth\n" in page and "- seed 2: `summary of seed 2`" in page
    assert page.rstrip().endswith(summary)


def test_one_seed_s_run_is_what_seed_and_out_give_it(tmp_path):
    args = bench.parse_args(["--quick", "--seeds", "3", "5", "--out", str(tmp_path / "out")])
    one = bench.seed_run_args(args, 5)
    alone = bench.parse_args(["--quick", "--seed", "5", "--out", str(tmp_path / "out" / "seed5")])
    assert vars(one) == vars(alone)
    assert args.out == tmp_path / "out" and args.seed == 0  # the invocation's own args untouched


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--seed", "1", "--seeds", "0", "1"], "argument --seeds: not allowed with argument --seed"),
        (["--seeds", "0", "1", "0"], "--seeds: a seed given twice: 0 1 0"),
        (["--seeds"], "argument --seeds: expected at least one argument"),
    ],
)
def test_seed_with_seeds_and_a_repeated_seed_are_parser_errors(flags, message, capsys):
    with pytest.raises(SystemExit) as exit_:
        bench.parse_args(flags)
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err
