"""benchmarks/ethucy.py's resume: a completed run is reused only when it was made with this invocation's
recipe. On fabricated ``scores.json`` files: no data, no training."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from benchmarks import ethucy as bench
from benchmarks.pedestrians.recipe import (
    CV,
    CV_NOISE,
    CV_RECIPES,
    FULL,
    HEADING_NOISE_GRID,
    PAPER,
    PAPER_PRIOR,
    QUICK,
    TRAINED,
    Budget,
    check_reused,
    recipe,
    recipe_differences,
    scored_on,
    slug,
    stale_runs,
    train_overrides,
)
from benchmarks.pedestrians.runs import SCORED_SPLITS
from benchmarks.pedestrians.scoring import METRICS, MODES
from mmf_rl.configuration import compose_config, save_config, to_container
from mmf_rl.models import check_loss_settings
from mmf_rl.objectives import LossConfig, default_loss_config
from mmf_rl.trainers.training import RUN_CONFIG
from tests.benchmarks.conftest import ethucy_fold_configs
from tests.conftest import run_bench

REPO = Path(__file__).resolve().parents[2]

ALL_ROWS = [*TRAINED, CV, CV_NOISE]


def bench_args(tmp_path: Path, out: str, *flags: str):
    return bench.parse_args(["--out", str(tmp_path / out), "--data", str(tmp_path / "data"), *flags])


def write_scores(args, fold: str, label: str, **fields) -> Path:
    path = args.out / fold / slug(label) / "scores.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"scores": {}, **fields}))
    return path


def complete_fold(args, budget: Budget, fold: str) -> None:
    """Every row of ``fold`` completed with ``budget``'s recipe, its figure drawn."""
    for label in ALL_ROWS:
        prior = {"prior_scores": {}} if label == PAPER else {}
        write_scores(args, fold, label, recipe=recipe(args, budget, fold, label), **prior)
    (args.out / fold / "forecasts.png").touch()


def test_completed_runs_of_this_recipe_are_reused_not_computed_again(tmp_path, monkeypatch):
    args = bench_args(tmp_path, "out", "--quick")
    complete_fold(args, QUICK, "eth")

    def must_not_run(*_):
        raise AssertionError("a completed run was computed again")

    monkeypatch.setattr(bench, "fold_data", lambda *_: (None, None))
    monkeypatch.setattr(bench, "run_trained", must_not_run)
    monkeypatch.setattr(bench, "run_constant_velocity", must_not_run)
    assert stale_runs(args, QUICK, ["eth"]) == []
    results = bench.run_fold(args, QUICK, "eth")
    assert list(results) == [*TRAINED, PAPER_PRIOR, CV, CV_NOISE]
    assert results[PAPER]["recipe"] == recipe(args, QUICK, "eth", PAPER)


def test_runs_moved_to_another_machine_keep_their_recipe(tmp_path):
    """Where the data, the cache and the runs live and the device are not the recipe."""
    args = bench_args(tmp_path, "out", "--quick")
    complete_fold(args, QUICK, "hotel")
    shutil.copytree(args.out, tmp_path / "moved")
    moved = bench.parse_args(
        [
            "--quick",
            "--out",
            str(tmp_path / "moved"),
            "--data",
            str(tmp_path / "elsewhere"),
            "--device",
            "cuda",
        ]
    )
    assert stale_runs(moved, QUICK, ["hotel"]) == []


def test_a_completed_run_of_another_mode_is_refused_before_anything_runs(tmp_path):
    full = bench_args(tmp_path, "out")
    path = write_scores(full, "eth", PAPER, recipe=recipe(full, FULL, "eth", PAPER))
    # No raw files: were the run let through, the conversion would fail at once instead of training.
    paths = ["--out", str(full.out), "--data", str(full.data), "--raw", str(tmp_path / "raw")]
    run = run_bench("ethucy", "--quick", *paths, cwd=tmp_path)
    assert run.returncode == 1, run.stderr[-3000:]
    assert f"{path.parent}: trainer.total_steps: expected 800, found 3000;" in run.stderr
    assert "use another --out, or delete a listed directory" in run.stderr
    assert path.is_file()  # nothing deleted
    assert not full.data.exists()  # refused before converting the data


def test_a_run_trained_before_a_default_changed_is_refused(tmp_path):
    """Its recipe (the overrides) is this one; its config.yaml holds the old default. The same old value
    of a loss setting a baseline does not read changes nothing."""
    args = bench_args(tmp_path, "out", "--quick")
    complete_fold(args, QUICK, "eth")
    args.data.mkdir()
    shutil.copy(REPO / "configs" / "data" / "push.yaml", args.data / "eth.yaml")  # stands in for the fold's
    for label in TRAINED:
        run_dir = args.out / "eth" / slug(label)
        cfg = compose_config("train", train_overrides(args, QUICK, "eth", label, run_dir))
        cfg.loss.detach_teacher = not cfg.loss.detach_teacher
        save_config(cfg, run_dir / RUN_CONFIG)
    assert stale_runs(args, QUICK, ["eth"]) == [
        f"{args.out / 'eth' / slug(PAPER)}: trained with loss.detach_teacher=True (now False)"
    ]


def test_another_model_recipe_names_every_differing_setting():
    paper, lstm = (list(TRAINED[label]) for label in (PAPER, "LF-LSTM"))
    assert recipe_differences(paper, lstm) == [
        "model: expected forecaster, found lf_lstm",
        "model.prior: expected learned, found absent",
        "model.learned_samples: expected 20, found 0",
    ]


def test_constant_velocity_rows_of_another_heading_noise_grid_are_refused(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    write_scores(args, "univ", CV, recipe=CV_RECIPES[CV])
    write_scores(args, "univ", CV_NOISE, recipe=["heading_noise_grid=[0.1, 0.2]"])
    assert stale_runs(args, QUICK, ["univ"]) == [
        f"{args.out / 'univ' / slug(CV_NOISE)}: heading_noise_grid: expected "
        f"{list(HEADING_NOISE_GRID)}, found [0.1, 0.2]"
    ]


def test_a_recipe_recorded_before_the_seed_was_overridden_trained_with_seed_0(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    settings = recipe(args, QUICK, "zara1", PAPER)
    assert "trainer.seed=0" in settings
    write_scores(args, "zara1", PAPER, recipe=[s for s in settings if not s.startswith("trainer.seed=")])
    assert stale_runs(args, QUICK, ["zara1"]) == []
    seed_1 = bench_args(tmp_path, "out", "--quick", "--seed", "1")
    assert stale_runs(seed_1, QUICK, ["zara1"]) == [
        f"{args.out / 'zara1' / slug(PAPER)}: trainer.seed: expected 1, found 0"
    ]


def test_a_scores_json_without_recipe_is_refused_as_unknown(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    write_scores(args, "hotel", "MulT")  # as written before the runs recorded their recipe
    with pytest.raises(SystemExit, match=r"hotel/mult: recipe unknown .*: it cannot be checked"):
        check_reused(args, QUICK, ["hotel"])
    assert (args.out / "hotel" / "mult" / "scores.json").is_file()


def test_what_a_run_writes_is_the_recipe_its_resume_checks(tmp_path, monkeypatch):
    """The rows as ``run_trained`` and ``run_constant_velocity`` write them, their training and scoring
    replaced by stand-ins: this recipe accepts them, the full mode's refuses the trained ones."""
    import benchmarks.pedestrians.scoring
    import mmf_rl
    import mmf_rl.configuration
    import mmf_rl.models

    monkeypatch.setattr(mmf_rl.configuration, "compose_config", lambda name, overrides: overrides)

    def train(overrides):  # the trainer makes the run directory
        Path(next(o for o in overrides if o.startswith("run_dir="))[len("run_dir=") :]).mkdir(parents=True)

    monkeypatch.setattr(mmf_rl, "train", train)
    monkeypatch.setattr(mmf_rl.models, "load_trained_model", lambda *_, **__: (None, None, None))
    monkeypatch.setattr(bench, "score", lambda *_, **__: {"all": {"min_ade_k": 1.0}})
    monkeypatch.setattr(bench, "prior_scores", lambda *_: {"all": {"min_ade_k": 2.0}})
    monkeypatch.setattr(benchmarks.pedestrians.scoring, "constant_velocity_model", lambda *_: None)
    monkeypatch.setattr(benchmarks.pedestrians.scoring, "best_heading_noise", lambda *_: (0.05, {0.05: 1.0}))
    args = bench_args(tmp_path, "out", "--quick")
    for label in TRAINED:
        bench.run_trained(args, QUICK, "zara1", label, None)
    bench.run_constant_velocity(args, "zara1", None)
    assert stale_runs(args, QUICK, ["zara1"]) == []
    refused = stale_runs(args, FULL, ["zara1"])
    assert [line.split(": ")[0] for line in refused] == [
        str(args.out / "zara1" / slug(label)) for label in TRAINED
    ]


def test_a_run_trained_before_the_windows_were_turned_is_refused_as_unturned(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    settings = recipe(args, QUICK, "eth", PAPER)
    assert "augment.rotation=180" in settings
    write_scores(args, "eth", PAPER, recipe=[s for s in settings if not s.startswith("augment.rotation=")])
    assert stale_runs(args, QUICK, ["eth"]) == [
        f"{args.out / 'eth' / slug(PAPER)}: augment.rotation: expected 180, found 0"
    ]


def test_a_paper_model_trained_before_the_learned_sampler_is_refused_as_one_without(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    settings = recipe(args, QUICK, "eth", PAPER)
    assert {"model.learned_samples=20", "sampler.steps=150"} <= set(settings)
    before = [s for s in settings if not s.startswith(("model.learned_samples=", "sampler."))]
    write_scores(args, "eth", PAPER, recipe=before)
    assert stale_runs(args, QUICK, ["eth"]) == [
        f"{args.out / 'eth' / slug(PAPER)}: model.learned_samples: expected 20, found 0; "
        "sampler.steps: expected 150, found 0; sampler.diversity_weight: expected 5.0, found 20.0; "
        "sampler.diversity_scale: expected 5.0, found 10.0"
    ]


def test_a_sampler_trained_with_other_diversity_weights_is_refused(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    settings = recipe(args, QUICK, "eth", PAPER)
    eth_weights = [s for s in settings if not s.startswith("sampler.diversity_")]  # the defaults were 20 / 10
    write_scores(args, "eth", PAPER, recipe=eth_weights)
    assert stale_runs(args, QUICK, ["eth"]) == [
        f"{args.out / 'eth' / slug(PAPER)}: sampler.diversity_weight: expected 5.0, found 20.0; "
        "sampler.diversity_scale: expected 5.0, found 10.0"
    ]


def test_a_budget_validates_exactly_its_evaluations():
    for budget in (QUICK, FULL):
        for steps in (budget.steps, budget.baseline_steps):
            assert steps // (steps // budget.evaluations) == budget.evaluations
    with pytest.raises(ValueError, match="baseline_steps=250 is not a multiple of evaluations=4"):
        Budget("odd", ("eth",), 800, 64, 250, 64, 150, 4)


def test_fold_configs_converted_before_the_planar_dims_were_declared_are_refused(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    args.data.mkdir(parents=True, exist_ok=True)
    for fold in QUICK.folds:
        (args.data / f"{fold}.yaml").write_text("target: {feature: observation.trajectory, dims: [0, 1]}\n")
    with pytest.raises(SystemExit, match=r"eth.yaml was converted by an older mmf-rl: .* convert again"):
        bench.ensure_data(args, QUICK.folds)


@pytest.mark.parametrize("budget", [QUICK, FULL])
@pytest.mark.parametrize("label", list(TRAINED))
def test_every_trained_model_is_given_only_loss_settings_its_loss_reads(tmp_path, budget, label):
    """The recipe is the training overrides but where the data and the run live, the protocol, and the
    windows the row is scored on: composed on the default data, the trainer's check of the loss settings
    sees what the benchmark's training sees."""
    args = bench_args(tmp_path, "out")
    settings = recipe(args, budget, "eth", label)
    assert settings[-2:] == ["protocol=probe", scored_on(args)] == ["protocol=probe", "window_set=trajectron"]
    cfg = compose_config("train", settings[:-2])
    check_loss_settings(
        to_container(cfg.model), LossConfig.from_dict(to_container(cfg.loss)), default_loss_config()
    )
    assert (f"loss.kl_warmup_steps={min(200, budget.steps // 5)}" in settings) == (label == PAPER)


def test_a_baselines_recipe_with_the_kl_warmup_it_never_read_is_reused(tmp_path):
    """Before the trainer refused them, every trained model was given the paper model's KL warm-up."""
    args = bench_args(tmp_path, "out", "--quick")
    for label in ("LF-LSTM", "MulT"):
        settings = recipe(args, QUICK, "hotel", label)
        assert not any(s.startswith("loss.") for s in settings)
        write_scores(args, "hotel", label, recipe=[*settings, "loss.kl_warmup_steps=60"])
    paper = recipe(args, QUICK, "hotel", PAPER)
    assert "loss.kl_warmup_steps=160" in paper
    write_scores(
        args,
        "hotel",
        PAPER,
        recipe=[s if not s.startswith("loss.") else "loss.kl_warmup_steps=60" for s in paper],
    )
    assert stale_runs(args, QUICK, ["hotel"]) == [
        f"{args.out / 'hotel' / slug(PAPER)}: loss.kl_warmup_steps: expected 160, found 60"
    ]


def test_rows_scored_on_another_window_set_are_refused_and_older_ones_were_on_trajectrons(tmp_path):
    args = bench_args(tmp_path, "out", "--quick")
    complete_fold(args, QUICK, "eth")
    social_gan = bench_args(tmp_path, "out", "--quick", "--window-set", "social_gan")
    assert stale_runs(social_gan, QUICK, ["eth"]) == [
        f"{args.out / 'eth' / slug(label)}: window_set: expected social_gan, found trajectron"
        for label in ALL_ROWS
    ]
    # Rows recorded before the window set was: scored on every window, Trajectron++'s set.
    for label in ALL_ROWS:
        settings = [s for s in recipe(args, QUICK, "hotel", label) if not s.startswith("window_set=")]
        write_scores(
            args, "hotel", label, recipe=settings, **({"prior_scores": {}} if label == PAPER else {})
        )
    assert stale_runs(args, QUICK, ["hotel"]) == []
    assert len(stale_runs(social_gan, QUICK, ["hotel"])) == len(ALL_ROWS)


def _scores(value: float) -> dict:
    return {mode: {m: value for m in METRICS} | {"windows": 181.0} for mode in MODES}


def test_the_page_says_which_window_set_each_row_is_scored_on(tmp_path):
    rows = {label: {"scores": _scores(0.5)} for label in [*TRAINED, PAPER_PRIOR, CV, CV_NOISE]}
    rows[CV_NOISE]["heading_noise"] = 0.1
    per_fold = {"eth": rows}
    averages = {"Average": {label: row["scores"] for label, row in rows.items()}}
    page = bench.markdown(per_fold, averages, QUICK, "social_gan", {})
    assert "Every row is scored on the `social_gan` window set: the trajectron windows whose" in page
    assert "## eth (181 test windows;" in page
    assert "| Social-STGCNN | 0.44 / 0.75 | social_gan |" in page
    assert "| AgentFormer (leak fixed) | 0.23 / 0.39 | trajectron |" in page


@pytest.mark.slow  # a converted ETH/UCY dataset (`ethucy_cut`), as every test reading one
def test_the_folds_val_and_test_windows_are_cut_to_the_window_set_its_training_ones_not(tmp_path, ethucy_cut):
    from mmf_rl.datasets import ethucy

    args = bench_args(tmp_path, "out", "--window-set", "social_gan")
    ethucy_fold_configs(ethucy_cut[1], args.data)
    data, _ = bench.fold_data(args, "eth")
    every, _ = bench.fold_data(bench_args(tmp_path, "out"), "eth")
    assert data.split_windows["train"].equal(every.split_windows["train"])
    for split in SCORED_SPLITS:
        assert 0 < len(data.split_windows[split]) < len(every.split_windows[split])
        assert data.split_windows[split].equal(ethucy.window_set_ids(every, split, "social_gan"))
