"""`mmf-rl train` + `mmf-rl eval` of the learned prior on a recording whose sensors fail in some windows;
evaluating its checkpoint with another eval latent; evaluating its save_pretrained export."""

import json
import shutil

import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from mmf_rl.datasets import DataConfig, WindowDataset
from mmf_rl.eval.evaluation import data_config_for_eval, first_shared_windows
from mmf_rl.eval.report import constant_velocity_warning
from mmf_rl.models import load_trained_model
from tests.conftest import SMALL_MODALITIES, push_train_overrides

NEW_COLUMNS = (
    "available",
    "minMSE@K (norm.)",
    "minADE@K",
    "minFDE@K",
    "NLL",
    "cover 50%",
    "cover 90%",
    "width 90%",
    "CRPS (norm.)",
)


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
        *push_train_overrides(faulty_push_root, base / "cache", run, steps=40, every=20),
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
        assert row["width_90"] > 0 and row["crps"] > 0
    assert rows["all"]["degradation"] == 0
    # The learned prior's latents depend on the present modalities: the t-SNE has something to show.
    assert (run / "eval" / "latent_tsne.png").stat().st_size > 1000
    # results.md warns exactly when the model loses to constant velocity.
    cv = json.loads((run / "eval" / "results.json").read_text())["constant_velocity"]
    loses = rows["all"]["mse"] > cv["mse"]
    assert ("loses to constant velocity" in (run / "eval" / "results.md").read_text()) == loses


def test_losing_to_constant_velocity_is_a_warning_naming_both_errors_and_the_fix():
    rows, cv = {"all": {"mse": 0.5}}, {"mse": 0.25}
    warning = constant_velocity_warning(rows, cv, relative=False)
    assert "0.5 against constant velocity's 0.25 (2.00x)" in warning
    assert "data.target.relative=true" in warning
    assert "data.target.relative=true" not in constant_velocity_warning(rows, cv, relative=True)
    assert constant_velocity_warning({"all": {"mse": 0.2}}, cv, relative=False) is None
    assert constant_velocity_warning(rows, None, relative=False) is None


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
            "ForecasterConfig.eval_latent must be one of ('mean', 'sample', 'predictive', 'posterior')",
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


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("split=tests", "split='tests': expected one of train, val, test"),
        ("num_samples=-1", "num_samples=-1: must be >= 0"),
        ("plot_windows=0", "plot_windows=0: must be >= 1, or pass plots=false"),
    ],
)
def test_eval_names_a_bad_setting_before_loading(learned_prior_run, capsys, override, message):
    out_dir = learned_prior_run / "bad_setting"
    assert cli(["eval", f"checkpoint={learned_prior_run}", override, f"out_dir={out_dir}"]) == 1
    assert capsys.readouterr().err.startswith(f"mmf-rl eval: error: {message}")
    assert not out_dir.exists()


@pytest.fixture(scope="module")
def exported(learned_prior_run, tmp_path_factory):
    """The run's last checkpoint exported with save_pretrained, as a user shares it."""
    model, _, _ = load_trained_model(learned_prior_run)
    path = tmp_path_factory.mktemp("exported") / "learned_prior"
    model.save_pretrained(path)
    return path


def results(path) -> dict:
    return json.loads((path / "results.json").read_text())


def assert_same_scores(mine: dict, reference: dict) -> None:
    """The same rows on the same windows with the same numbers (to 1e-6)."""
    assert mine["subsets"].keys() == reference["subsets"].keys()
    for name, row in mine["subsets"].items():
        assert row.keys() == reference["subsets"][name].keys(), name
        for metric, value in row.items():
            assert value == pytest.approx(reference["subsets"][name][metric], abs=1e-6), (name, metric)
    assert mine["constant_velocity"] == pytest.approx(reference["constant_velocity"], abs=1e-6)


def test_eval_of_a_save_pretrained_export_scores_like_the_run(learned_prior_run, exported, capsys):
    run, common = learned_prior_run, ["num_samples=5", "plots=false"]
    assert cli(["eval", f"checkpoint={run}", *common, f"out_dir={run / 'eval_as_run'}"]) == 0
    assert cli(["eval", f"checkpoint={exported}", *common]) == 0
    capsys.readouterr()
    reference, mine = results(run / "eval_as_run"), results(exported / "eval")  # default: DIR/eval
    assert_same_scores(mine, reference)
    assert (reference["model_format"], reference["step"]) == ("checkpoint", 40)
    assert (mine["model_format"], mine["step"]) == ("save_pretrained", None)
    assert mine["checkpoint"] == str(exported)
    assert mine["data_root"] == reference["data_root"] and mine["eval_latent"] == "mean"
    unknown = f"training step unknown: {exported} is a save_pretrained directory"
    assert any(note.startswith(unknown) for note in mine["notes"])
    assert unknown in (exported / "eval" / "results.md").read_text()


def test_eval_of_a_moved_export_with_data_root_and_another_eval_latent(
    learned_prior_run, exported, faulty_push_root, tmp_path, capsys
):
    """A model from another machine: its saved data root does not exist here; data_root= says where
    the data is. The eval latent override applies to an export as to a checkpoint."""
    moved = tmp_path / "downloaded"
    shutil.copytree(exported, moved, ignore=shutil.ignore_patterns("eval"))
    data_config = json.loads((moved / "data_config.json").read_text())
    saved_root = tmp_path / "elsewhere" / "push"
    (moved / "data_config.json").write_text(json.dumps({**data_config, "root": str(saved_root)}))
    assert cli(["eval", f"checkpoint={moved}", "plots=false"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"mmf-rl eval: error: the data config saved with {moved} reads the dataset at ")
    assert f"{saved_root}, which does not exist on this machine" in err and "pass data_root=" in err
    assert not (moved / "eval").exists()

    overrides = {"eval_latent": "predictive", "predictive_samples": 4}
    latent = [f"{k}={v}" for k, v in overrides.items()] + ["num_samples=0", "plots=false"]
    run = learned_prior_run
    assert cli(["eval", f"checkpoint={run}", *latent, f"out_dir={run / 'eval_predictive'}"]) == 0
    assert cli(["eval", f"checkpoint={moved}", *latent, f"data_root={faulty_push_root}"]) == 0
    mine, reference = results(moved / "eval"), results(run / "eval_predictive")
    assert_same_scores(mine, reference)
    assert (mine["eval_latent"], mine["predictive_samples"]) == ("predictive", 4)
    assert mine["latent_overrides"] == reference["latent_overrides"] == overrides
    assert mine["data_root"] == str(faulty_push_root)
    # The override is the eval's alone: the export still says how it was trained.
    assert json.loads((moved / "config.json").read_text())["eval_latent"] == "mean"


KINDS = "expected a run directory, its checkpoints/, one checkpoint (meta.json) or a directory written by"


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        ("missing", "{path} does not exist; " + KINDS),
        ("empty", "{path} is not a trained model (it holds nothing); " + KINDS),
        ("other files", "{path} is not a trained model (it holds notes.txt, scores/); " + KINDS),
        ("empty run", "{path}/checkpoints is not a trained model (it holds nothing); " + KINDS),
        ("no data config", "{path} holds a saved model without data_config.json (its normalisation"),
        ("no stats", "{path} holds a saved model without normalization.safetensors (its normalisation"),
        ("no weights", "{path} is not a saved mmf-rl model: {path}/model.safetensors does not exist"),
        (
            "bad latent",
            "eval_latent=median for the 'forecaster' model of {path}: ForecasterConfig.eval_latent",
        ),
        (
            "outside",
            "out_dir=/tmp/elsewhere resolves to /tmp/elsewhere, outside the save_pretrained directory",
        ),
    ],
)
def test_eval_names_what_is_wrong_with_the_directory(exported, tmp_path, capsys, setup, message):
    path = tmp_path / "model"
    args = []
    if setup in ("other files", "empty", "empty run"):
        path.mkdir()
    if setup == "other files":
        (path / "notes.txt").write_text("not a model")
        (path / "scores").mkdir()
    if setup == "empty run":
        (path / "checkpoints").mkdir()
    if setup in ("no data config", "no stats", "no weights", "bad latent", "outside"):
        shutil.copytree(exported, path, ignore=shutil.ignore_patterns("eval"))
        removed = {"no data config": "data_config.json", "no stats": "normalization.safetensors"}
        removed["no weights"] = "model.safetensors"
        if setup in removed:
            (path / removed[setup]).unlink()
        args = {"bad latent": ["eval_latent=median"], "outside": ["out_dir=/tmp/elsewhere"]}.get(setup, [])
    assert cli(["eval", f"checkpoint={path}", *args]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"mmf-rl eval: error: {message.format(path=path)}"), err
    assert "\n" not in err.strip() and not (path / "eval").exists()


def test_a_model_in_the_hugging_face_cache_needs_an_out_dir_elsewhere(
    exported, tmp_path, monkeypatch, capsys
):
    """from_pretrained's copy of a hub model (a snapshot in the hub cache) is not a place for results."""
    import huggingface_hub.constants

    cache = tmp_path / "hub"
    snapshot = cache / "models--user--push" / "snapshots" / "0123abc"
    shutil.copytree(exported, snapshot, ignore=shutil.ignore_patterns("eval"))
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_CACHE", str(cache))
    assert cli(["eval", f"checkpoint={snapshot}", "plots=false"]) == 1
    err = capsys.readouterr().err
    assert err.startswith(
        f"mmf-rl eval: error: {snapshot} is in the Hugging Face cache ({cache}); pass out_dir="
    )
    assert not (snapshot / "eval").exists()


def test_eval_scores_data_that_lost_a_modality_on_most_frames(tmp_path):
    """The more-than-half-absent error guards training; an evaluation scores what the data holds."""
    saved = {
        "root": str(tmp_path),
        "modalities": {"cam": "observation.images.cam", "state": {"feature": "observation.state"}},
        "target": {"feature": "observation.state"},
    }
    config = data_config_for_eval(saved, None, source=None)
    assert all(m.allow_absent for m in config.modalities.values())
    assert saved["modalities"]["state"] == {"feature": "observation.state"}, (
        "the saved config is left as it was"
    )


def test_plots_draw_windows_every_subset_can_score_and_refuse_batches_without_one(mixed_batch):
    names = [s.name for s in SMALL_MODALITIES]
    singles = [(f"only_{name}", {m: m == name for m in names}) for name in names]
    present = torch.stack([mixed_batch.get(keys.present_key(name)) for name in names])
    shared = first_shared_windows([mixed_batch], singles)
    assert shared.shape[0] == int(present.all(0).sum()) == 1
    assert all(bool(shared.get(keys.present_key(name)).all()) for name in names)
    with pytest.raises(ValueError, match="no window can be scored in every presence subset"):
        first_shared_windows([mixed_batch[~present.all(0)]], singles)
