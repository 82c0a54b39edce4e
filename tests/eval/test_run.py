"""`mmf-rl train` + `mmf-rl eval` of the learned prior on a recording whose sensors fail in some windows;
evaluating its checkpoint with another eval latent."""

import json
from pathlib import Path

import pytest
import torch

from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.configuration import ConfigError
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.eval.run import model_config_for_eval
from mmf_rl.models import build_model, saved_config
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, TARGET_DIM, push_train_overrides

NEW_COLUMNS = ("available", "minMSE@K (norm.)", "minADE@K", "minFDE@K", "NLL", "cover 50%", "cover 90%")


@pytest.fixture(scope="module")
def faulty_push_root(tmp_path_factory):
    """A push recording with sensor faults written as data (NaN force spans, frozen and black frames)."""
    from mmf_rl.record import RecordConfig, record

    root = tmp_path_factory.mktemp("faulty") / "push"
    return record(RecordConfig(out=root, episodes=6, steps=40, image_size=32, seed=3, faults=True))


@pytest.fixture(scope="module")
def learned_prior_run(faulty_push_root, tmp_path_factory):
    """A tiny learned-prior forecaster trained by `mmf-rl train` on the faulty recording."""
    base = tmp_path_factory.mktemp("learned_prior")
    run = base / "run"
    overrides = [
        *push_train_overrides(faulty_push_root, base / "cache", run, steps=40),
        "model.prior=learned",
        "loss.max_dropped=null",
        "loss.gsnn_weight=0.5",
        "loss.dropped_nll_weight=0.5",
    ]
    assert cli(["train", *overrides]) == 0
    return run


def test_learned_prior_eval_pairs_subsets_on_windows_with_failed_sensors(learned_prior_run, capsys):
    run = learned_prior_run
    assert cli(["eval", f"checkpoint={run}", "num_samples=5", "plot_windows=4"]) == 0
    out = capsys.readouterr().out
    header = next(line for line in out.splitlines() if line.startswith("| subset |"))
    assert all(f" {column} |" in header for column in NEW_COLUMNS), header

    # The windows every row is scored on: the test windows where no sensor failed.
    data = WindowDataset(DataConfig.from_dict(load_checkpoint(run / "checkpoints").meta["config"]["data"]))
    test = data.split_windows["test"]
    presence = {name: mask[test] for name, mask in data.presence.items()}
    shared = torch.stack(list(presence.values())).all(0)
    assert 0 < int(shared.sum()) < len(test), "the faults should remove a sensor from some test windows"

    rows = json.loads((run / "eval" / "results.json").read_text())["subsets"]
    assert set(rows) == {
        "all",
        "without_image",
        "without_force",
        "without_proprio",
        "only_image",
        "only_force",
        "only_proprio",
    }
    assert {row["windows"] for row in rows.values()} == {float(shared.sum())}
    assert rows["all"]["windows_available"] == len(test)
    for name, mask in presence.items():
        assert rows[f"only_{name}"]["windows_available"] == int(mask.sum())
    for row in rows.values():
        assert 0 <= row["coverage_50"] <= row["coverage_90"] <= 1
        assert row["min_mse_k"] >= 0 and row["min_fde_k"] >= 0 and row["nll"] == row["nll"]
    assert rows["all"]["degradation"] == 0
    # The learned prior's latents depend on the present modalities: the t-SNE has something to show.
    assert (run / "eval" / "latent_tsne.png").stat().st_size > 1000


def test_eval_scores_a_trained_checkpoint_with_another_eval_latent(learned_prior_run, capsys):
    run = learned_prior_run
    common = [f"checkpoint={run}", "num_samples=0", "plots=false"]
    assert cli(["eval", *common, f"out_dir={run / 'as_trained'}"]) == 0
    override = ["eval_latent=predictive", "predictive_samples=4"]
    assert cli(["eval", *common, *override, f"out_dir={run / 'predictive'}"]) == 0
    out = capsys.readouterr().out
    as_trained = json.loads((run / "as_trained" / "results.json").read_text())
    predictive = json.loads((run / "predictive" / "results.json").read_text())
    assert (as_trained["eval_latent"], as_trained["predictive_samples"], as_trained["latent_overrides"]) == (
        "mean",
        None,
        {},
    )
    assert predictive["eval_latent"] == "predictive" and predictive["predictive_samples"] == 4
    assert predictive["latent_overrides"] == {"eval_latent": "predictive", "predictive_samples": 4}
    header = "Forecast latent: eval_latent=predictive, predictive_samples=4 (set by this eval: "
    assert header in (run / "predictive" / "results.md").read_text() and header in out
    assert "eval_latent=mean (as trained)" in (run / "as_trained" / "results.md").read_text()
    # The same windows, scored with other forecasts: the mixture's mean and its wider scale.
    for name, row in predictive["subsets"].items():
        reference = as_trained["subsets"][name]
        assert row["windows"] == reference["windows"]
        assert row["mse"] != reference["mse"] and row["nll"] != reference["nll"], name
    # The override is the eval's alone: the checkpoint still says how it was trained.
    assert load_checkpoint(run / "checkpoints").meta["model_config"]["eval_latent"] == "mean"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        (
            "eval_latent=median",
            "ForecasterConfig.eval_latent must be one of ('mean', 'sample', 'predictive')",
        ),
        ("predictive_samples=3", "ForecasterConfig.predictive_samples must be an even integer >= 2"),
    ],
)
def test_eval_names_a_bad_latent_override(learned_prior_run, capsys, override, message):
    out_dir = learned_prior_run / f"bad_{override.split('=')[0]}"
    assert cli(["eval", f"checkpoint={learned_prior_run}", override, f"out_dir={out_dir}"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"mmf-rl eval: error: {override} for the 'forecaster' model of ") and message in err
    assert not out_dir.exists()


def test_latent_override_of_a_baseline_names_the_model():
    """A baseline without the setting refuses it by name; the MVAE takes the eval latents it has."""
    checkpoint = Path("runs/x/checkpoints/step_6")
    saved = {
        name: saved_config(name, build_model({"name": name}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM))
        for name in ("lf_lstm", "mvae")
    }
    with pytest.raises(
        ConfigError, match=r"eval_latent=predictive: the 'lf_lstm' model of runs/x.* no setting eval_latent"
    ):
        model_config_for_eval(saved["lf_lstm"], {"eval_latent": "predictive"}, checkpoint)
    with pytest.raises(ConfigError, match="the 'mvae' model of .* has no setting predictive_samples"):
        model_config_for_eval(saved["mvae"], {"predictive_samples": 8}, checkpoint)
    with pytest.raises(ConfigError, match="'mvae' model .*MVAEConfig.eval_latent must be 'mean' or 'sample'"):
        model_config_for_eval(saved["mvae"], {"eval_latent": "predictive"}, checkpoint)
    assert (
        model_config_for_eval(saved["mvae"], {"eval_latent": "sample"}, checkpoint)["eval_latent"] == "sample"
    )
    assert model_config_for_eval(saved["lf_lstm"], {}, checkpoint) == saved["lf_lstm"]
