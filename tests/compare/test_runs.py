"""mmf_rl.compare.runs: the training overrides, the checks before any training, the per-window errors
and the training rate of a run."""

from __future__ import annotations

import copy
import dataclasses
import json
import runpy
import shutil
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from mmf_rl.compare import entries, runs
from mmf_rl.compare.entries import Budget, Entry, Study
from mmf_rl.configuration import save_config
from mmf_rl.models import MODELS
from mmf_rl.objectives import default_loss_config
from mmf_rl.trainers.training import RUN_CONFIG
from tests.compare.helpers import PUSH_MODALITIES

REPO = Path(__file__).resolve().parents[2]


STEPS = 100  # a warm-up of min(200, 100 // 5) = 20 steps, not the loss config's 200


def study(tmp_path: Path, chosen=(entries.PAPER,), image_size: int | None = 32) -> Study:
    return Study(
        out=tmp_path / "out",
        budget=Budget(steps=STEPS, batch_size=32, seeds=(0,), image_size=image_size),
        entries=tuple(chosen),
        modalities=tuple(PUSH_MODALITIES),
        data_overrides=(f"data.root={tmp_path / 'data'}",),
    )


def test_the_data_overrides_follow_the_entrys_and_the_budget_follows_them(tmp_path):
    s = study(tmp_path)
    overrides = runs.train_overrides(entries.MULT, 3, s, tmp_path / "run", ("+data.missing.image=1.0",))
    assert overrides[:4] == [
        "model=mult",
        "+data.missing.image=1.0",
        f"data.root={tmp_path / 'data'}",
        f"data.cache_dir={tmp_path / 'out' / 'cache'}",
    ]
    cfg = runs.compose_train(entries.MULT, 3, s, tmp_path / "run")
    assert (cfg.trainer.total_steps, cfg.trainer.batch_size, cfg.trainer.seed) == (STEPS, 32, 3)
    assert list(cfg.data.image_size) == [32, 32] and cfg.model.name == "mult"
    default_size = runs.compose_train(entries.PAPER, 0, study(tmp_path, image_size=None), tmp_path / "run")
    assert list(default_size.data.image_size) == [64, 64]  # the data config's


@pytest.fixture(scope="module")
def composed_once(tmp_path_factory):
    """A directory for the studies of the tests below that only compose entries; while this module runs,
    ``runs.compose_train`` composes each distinct run config once (Hydra takes ~0.3 s a config; the
    catalogue, the benchmarks' entries and the catalogue again in ``check_entries`` are ~180) and hands
    every later call with the same overrides a copy of it."""
    compose_train, composed = runs.compose_train, {}

    def composed_once(entry, seed, s, run_dir, extra=()):
        key = (tuple(runs.train_overrides(entry, seed, s, run_dir, extra)), s.config_dirs, s.budget.steps)
        if key not in composed:
            composed[key] = compose_train(entry, seed, s, run_dir, extra)
        return copy.deepcopy(composed[key])

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(runs, "compose_train", composed_once)
        yield tmp_path_factory.mktemp("composed")


def test_the_kl_warmup_goes_to_the_entries_whose_loss_has_a_kl(composed_once):
    # A KL weighted 0 (mult_gap's deterministic paper model) has none to warm up.
    no_kl = Entry("paper, no KL", "ablation", ("model=forecaster", "loss=no_mis", "loss.kl_weight=0"))
    chosen = (*entries.CATALOGUE, no_kl)
    s = study(composed_once, chosen)
    runs.check_entries(s)  # the catalogue composes, and sets only what its models read
    composed = {e.label: runs.compose_train(e, 0, s, s.out / "check") for e in chosen}  # as checked
    warmup = {label: cfg.loss.kl_warmup_steps for label, cfg in composed.items()}
    # LF-LSTM's and MulT's entries (zero-fill, retrained, trained for missing sensors, the recommended
    # preset) train without a KL.
    models = {label: cfg.model.name for label, cfg in composed.items()}
    not_warmed = {label for label, name in models.items() if name in ("lf_lstm", "mult")} | {no_kl.label}
    assert len(not_warmed) == 12
    assert {label for label, steps in warmup.items() if steps != 100 // 5} == not_warmed
    assert {warmup[label] for label in not_warmed} == {default_loss_config().kl_warmup_steps}


def test_entries_are_checked_against_the_configs_before_any_training(composed_once):
    runs.check_entries(study(composed_once, entries.CATALOGUE))
    bogus = Entry("paper typo", "variant", ("model=forecaster", "model.fusoin=sum"))
    with pytest.raises(ValueError, match=r"'paper typo' \(model=forecaster model.fusoin=sum\)"):
        runs.check_entries(study(composed_once, (entries.PAPER, bogus)))
    ignored = Entry("MulT best-of-K", "zero-fill", ("model=mult", "loss.best_of_k_weight=1"))
    with pytest.raises(
        ValueError,
        match=r"'MulT best-of-K' \(model=mult loss.best_of_k_weight=1\): loss.best_of_k_weight=1 is",
    ):
        runs.check_entries(study(composed_once, (entries.PAPER, ignored)))


@pytest.fixture
def benchmark_entries():
    """A benchmark script's ``ENTRIES``, loaded as ``mmf-rl bench`` runs it (some register models of
    their own: the built-in ones only are left registered after)."""
    before = dict(MODELS)
    yield lambda name: runpy.run_path(str(REPO / "benchmarks" / f"{name}.py"), run_name="entries")["ENTRIES"]
    MODELS.clear()
    MODELS.update(before)


@pytest.mark.parametrize("benchmark", ["accuracy", "mult_gap", "real_humanoid"])
def test_every_benchmark_entry_sets_only_loss_options_its_model_reads(
    benchmark, benchmark_entries, composed_once
):
    runs.check_entries(study(composed_once, benchmark_entries(benchmark)))


def complete_run(s: Study, entry: Entry, steps: int = STEPS, **changes) -> Path:
    """A completed run of ``entry`` (seed 0) in ``s.out`` as ``run_one`` leaves it, its composed config
    with ``changes`` (dotted keys) applied."""
    run_dir = s.out / entries.slug(entry.label) / "seed0"
    cfg = runs.compose_train(entry, 0, s, run_dir)
    for key, value in changes.items():
        OmegaConf.update(cfg, key, value)
    save_config(cfg, run_dir / RUN_CONFIG)
    result = run_dir / "eval" / "window_errors.json"
    result.parent.mkdir(parents=True)
    result.write_text(json.dumps({"steps": steps, "batch_size": 32, "subsets": {}}))
    return run_dir


def test_completed_runs_of_another_budget_are_refused(tmp_path):
    s = study(tmp_path)
    complete_run(s, entries.PAPER)
    runs.check_reused(s)
    shutil.rmtree(s.out)
    complete_run(s, entries.PAPER, steps=3)
    with pytest.raises(ValueError, match=r"paper/seed0: 3 steps of batch 32\n.*use another --out"):
        runs.check_reused(s)


def test_completed_runs_trained_with_another_config_are_refused(tmp_path):
    # A default changed since the run trained reads as a change too.
    s = study(tmp_path)
    complete_run(s, entries.PAPER, **{"loss.detach_teacher": True, "model.d_model": 32})
    with pytest.raises(
        ValueError, match=r"paper/seed0: trained with loss.detach_teacher=True \(now False\), "
    ):
        runs.check_reused(s)


def test_a_run_moved_to_another_out_or_changed_where_its_model_ignores_it_is_reused(tmp_path):
    s = study(tmp_path, (entries.PAPER, entries.LF_LSTM))
    complete_run(s, entries.LF_LSTM, **{"loss.detach_teacher": True})  # L_mis: not LF-LSTM's loss
    complete_run(s, entries.PAPER)
    moved = dataclasses.replace(s, out=tmp_path / "elsewhere")  # another run_dir and cache_dir
    shutil.move(s.out, moved.out)
    runs.check_reused(moved)


def test_training_rate_is_the_last_logged_throughput(tmp_path):
    path = tmp_path / "logs" / "scalars" / "train" / "samples_per_s.csv"
    path.parent.mkdir(parents=True)
    path.write_text("25,410.5\n50,402.25\n")
    assert runs.training_rate(tmp_path) == 402.25


def evaluation(run: Path, *overrides: str) -> dict:
    from mmf_rl.configuration import compose_config
    from mmf_rl.eval.evaluation import evaluate

    return evaluate(compose_config("eval", [f"checkpoint={run}", "plots=false", "num_samples=0", *overrides]))


def test_window_errors_average_to_the_evaluations_mse_on_recorded_push_data(push_forecaster_run, tmp_path):
    """The comparison's own pass over the test windows (per-window errors, with their episodes) scores
    the same windows the same way as `mmf-rl eval`, on data recorded by the project's recorder."""
    from mmf_rl.checkpoint import load_checkpoint
    from mmf_rl.datasets import DataConfig, WindowDataset

    run = push_forecaster_run
    summary = evaluation(run, f"out_dir={tmp_path / 'eval'}", "allow_outside_run_dir=true")
    errors = runs.window_errors(run, "cpu", batch_size=7)  # batches that do not divide the split
    assert set(errors) == set(summary["subsets"])
    trained = load_checkpoint(run / "checkpoints", with_trainer_state=False).meta["config"]["data"]
    data = WindowDataset(DataConfig.from_dict(trained))
    for name, rows in errors.items():
        metrics = summary["subsets"][name]
        assert len(rows["squared_error"]) == metrics["windows"]
        mean = sum(rows["squared_error"]) / len(rows["squared_error"])
        assert mean == pytest.approx(metrics["mse"], rel=1e-5)
        assert set(rows["episode"]) <= set(data.split_episodes["test"])
        assert rows["episode"] == data.window_episode[torch.tensor(rows["window"])].tolist()
    runs.check_agreement(run, errors, summary)
    summary["subsets"]["all"]["mse"] *= 1.01
    with pytest.raises(RuntimeError, match="subset all: the per-window errors average"):
        runs.check_agreement(run, errors, summary)


def test_train_mse_scores_training_windows_as_eval_does_on_recorded_push_data(push_forecaster_run, tmp_path):
    """All training windows drawn: the evaluation's MSE of the train split with every sensor. Fewer: a
    subset drawn the same way every time."""
    from mmf_rl.checkpoint import load_checkpoint
    from mmf_rl.datasets import DataConfig, WindowDataset

    run = push_forecaster_run
    out = [f"out_dir={tmp_path / 'eval'}", "allow_outside_run_dir=true"]
    expected = evaluation(run, "split=train", *out)["subsets"]["all"]
    trained = load_checkpoint(run / "checkpoints", with_trainer_state=False).meta["config"]["data"]
    windows = len(WindowDataset(DataConfig.from_dict(trained)).split_windows["train"])
    assert expected["windows"] == windows
    assert runs.train_mse(run, "cpu", windows=windows, batch_size=7) == pytest.approx(
        expected["mse"], rel=1e-5
    )
    drawn = runs.train_mse(run, "cpu", windows=windows // 2)
    assert drawn == pytest.approx(runs.train_mse(run, "cpu", windows=windows // 2, batch_size=5), rel=1e-6)
    assert drawn != pytest.approx(expected["mse"], rel=1e-6)
