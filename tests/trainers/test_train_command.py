import json
import shutil
from pathlib import Path

import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import (
    LAST_POINTER,
    list_checkpoints,
    load_checkpoint,
)
from mmf_rl.cli import main as cli
from mmf_rl.configuration import compose_config, config_dir, to_container
from mmf_rl.datasets import WindowDataset
from mmf_rl.models import build_loss, load_trained_model
from mmf_rl.objectives import output_distribution_of
from mmf_rl.trainers.training import TrainRunConfig, check_loss_settings_read
from tests.conftest import file_states, push_train_overrides, small_registered_model
from tests.reliability.conftest import edit_frames, push_data_config


@pytest.fixture
def overrides(recorded_push_root, push_cache_dir, tmp_path):
    """Overrides of a tiny run in ``tmp_path / run`` on the session's recording, reading the session's
    window cache (built once: these tests are not about building it)."""
    return lambda run, **kw: push_train_overrides(recorded_push_root, push_cache_dir, tmp_path / run, **kw)


@pytest.fixture
def trained(push_forecaster_run, recorded_push_root, push_cache_dir, tmp_path):
    """The session's tiny run (`mmf-rl train` with `push_train_overrides`, 6 steps) copied to
    ``tmp_path / "run"``, and the overrides that trained it there: for the tests that would train that
    run themselves only to read, evaluate, resume or damage it."""
    run = Path(shutil.copytree(push_forecaster_run, tmp_path / "run"))
    return run, push_train_overrides(recorded_push_root, push_cache_dir, run)


def test_train_then_eval_writes_checkpoint_logs_table_and_plots(trained, capsys):
    run, _ = trained
    checkpoint = load_checkpoint(run / "checkpoints")
    assert checkpoint.step == 6 and checkpoint.meta["model_config"]["name"] == "forecaster"
    assert {"target/mean", "target/std", "force/mean"} <= set(checkpoint.tensors)
    assert (run / "config.yaml").is_file() and (run / "logs" / "scalars" / "train" / "loss.csv").is_file()

    assert cli(["eval", f"checkpoint={run}", "num_samples=3", "plot_windows=2"]) == 0
    out = capsys.readouterr().out
    assert "| all |" in out and "| without_image |" in out and "| constant velocity |" in out
    results = json.loads((run / "eval" / "results.json").read_text())
    assert set(results["subsets"]) >= {
        "all",
        "without_image",
        "without_force",
        "without_proprio",
        "only_image",
    }
    assert results["subsets"]["all"]["degradation"] == 0
    assert all(v["min_ade_k"] <= v["ade"] * 1.5 for v in results["subsets"].values())
    for plot in ("error_per_subset.png", "forecasts.png"):
        assert (run / "eval" / plot).stat().st_size > 1000
    # The standard prior decodes every test forecast from z = 0: there is no latent to plot, and it says so.
    assert not (run / "eval" / "latent_tsne.png").exists() and "no latent t-SNE" in out


def test_train_with_an_output_family_then_eval_and_calibrate_read_it_from_the_run(
    overrides, tmp_path, capsys
):
    """``model.output_distribution`` is written once, at training: the checkpoint's config carries it, and
    the calibration at the end, `mmf-rl calibrate` and `mmf-rl eval` read the forecast with it."""
    family = ["model.output_distribution=student_t", "model.output_df=3"]
    assert cli(["train", *overrides("run"), *family]) == 0
    run = tmp_path / "run"
    checkpoint = load_checkpoint(run / "checkpoints")
    saved = checkpoint.meta["model_config"]
    assert (saved["output_distribution"], saved["output_df"]) == ("student_t", 3)
    assert checkpoint.meta["calibration"]["output_distribution"] == "student_t (df 3)"
    assert output_distribution_of(load_trained_model(run / "model")[0]).describe() == "student_t (df 3)"
    assert cli(["calibrate", f"checkpoint={run}", "min_windows=4"]) == 0
    assert (
        load_checkpoint(run / "checkpoints").meta["calibration"]["output_distribution"] == "student_t (df 3)"
    )
    assert cli(["eval", f"checkpoint={run}", "num_samples=0", "plots=false"]) == 0
    capsys.readouterr()
    assert (
        json.loads((run / "eval" / "results.json").read_text())["output_distribution"] == "student_t (df 3)"
    )
    assert "Forecast distribution: student_t (df 3)" in (run / "eval" / "results.md").read_text()


def test_existing_run_is_never_overwritten_and_resume_needs_same_config(trained, capsys):
    run, overrides = trained
    before = file_states(run)
    assert cli(["train", *overrides]) == 1
    assert "already holds a trained run; pass resume=true" in capsys.readouterr().err
    assert cli(["train", *overrides, "resume=true", "model.d_latent=6"]) == 1
    err = capsys.readouterr().err
    assert "differs from" in err and "model.d_latent: 4 -> 6" in err
    assert file_states(run) == before, "neither command changed the run"


def test_augment_workers_may_change_when_a_run_resumes(overrides, tmp_path):
    augmented = ["train", *overrides("run"), "augment=lerobot"]
    assert cli([*augmented, "augment.workers=1"]) == 0
    assert cli([*augmented, "augment.workers=0", "resume=true"]) == 0  # the batches are the same
    assert cli([*augmented, "augment.max_num_transforms=2", "resume=true"]) == 1


def test_a_run_saved_before_a_setting_existed_resumes_with_a_warning_naming_it(trained):
    import yaml

    run, overrides = trained
    config = run / "config.yaml"
    saved = yaml.safe_load(config.read_text())
    del saved["model"]["predictive_samples"]  # as an older mmf-rl wrote it
    config.write_text(yaml.safe_dump(saved))
    with pytest.warns(UserWarning, match=r"predates the settings model\.predictive_samples=16"):
        assert cli(["train", *overrides, "resume=true"]) == 0
    assert load_checkpoint(run / "checkpoints").step == 6


def test_a_run_saved_before_decoder_input_resumes_the_tokens_decoder_it_trained(overrides, tmp_path):
    """A run begun before ``model.decoder_input`` existed trained the paper's ``tokens`` decoder, and its
    config.yaml and checkpoints lack the setting. Resumed half-way, it continues that decoder: the run's
    model group is read as a saved model's (``SAVED_BEFORE``), not as today's default ``mixed`` built on
    the weights trained with ``tokens``."""
    import yaml

    assert cli(["train", *overrides("run"), "model.decoder_input=tokens"]) == 0  # checkpoints at 3 and 6
    run = tmp_path / "run"
    config = run / "config.yaml"
    saved = yaml.safe_load(config.read_text())
    del saved["model"]["decoder_input"]  # as an older mmf-rl wrote it
    config.write_text(yaml.safe_dump(saved))
    checkpoints = list_checkpoints(run / "checkpoints")
    for checkpoint in checkpoints:
        meta = json.loads((checkpoint / "meta.json").read_text())
        del meta["model_config"]["decoder_input"], meta["config"]["model"]["decoder_input"]
        (checkpoint / "meta.json").write_text(json.dumps(meta))
    shutil.rmtree(checkpoints[-1])  # killed after step 3: steps 4-6 are trained again
    (run / "checkpoints" / LAST_POINTER).write_text(checkpoints[0].name + "\n")
    with pytest.warns(UserWarning, match=r"predates the settings .*model\.decoder_input='tokens'"):
        assert cli(["train", *overrides("run"), "resume=true"]) == 0
    assert load_checkpoint(run / "checkpoints").step == 6
    assert load_checkpoint(run / "checkpoints").meta["model_config"]["decoder_input"] == "tokens"
    assert json.loads((run / "model" / "config.json").read_text())["decoder_input"] == "tokens"
    assert "decoder_input" not in yaml.safe_load(config.read_text())["model"]  # still read as saved


def lf_lstm_overrides(overrides, run: str, **kw) -> list[str]:
    """``overrides`` for a tiny LF-LSTM (the forecaster's sizes it has not replaced by its own)."""
    return [
        *(o for o in overrides(run, **kw) if not o.startswith("model.")),
        "model=lf_lstm",
        "model.d_model=16",
        "model.head_hidden=32",
    ]


def shipped(group: str) -> list[str]:
    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


PAPER_MODEL_USES = [
    ("model=forecaster",),
    ("model=forecaster", "model.prior=learned"),  # ETH/UCY's, mmf-rl compare's
]
# The models each shipped loss config trains in the README and the benchmarks.
SHIPPED_LOSS_USES = {
    "default": [*((f"model={option}",) for option in shipped("model")), *PAPER_MODEL_USES[1:]],
    "no_mis": [
        *PAPER_MODEL_USES,
        ("model=forecaster", "loss.kl_weight=0", "model.eval_latent=posterior"),  # mult_gap's deterministic
    ],
}


def test_every_shipped_loss_config_has_its_uses_listed():
    assert sorted(SHIPPED_LOSS_USES) == shipped("loss")


@pytest.mark.parametrize(
    "loss, model",
    [(loss, model) for loss, uses in SHIPPED_LOSS_USES.items() for model in uses],
    ids=lambda value: " ".join(value) if isinstance(value, tuple) else value,
)
def test_every_shipped_loss_config_trains_the_models_it_is_used_with(loss, model):
    # The loss config group warms the ELBO's KL up; LF-LSTM and MulT, trained without it, get that too,
    # and so does a KL weighted 0.
    cfg = compose_config("train", [*model, f"loss={loss}"])
    run = TrainRunConfig.from_config(cfg)
    check_loss_settings_read(run)
    name, settings = cfg.model.name, {k: v for k, v in to_container(cfg.model).items() if k != "name"}
    build_loss(name, small_registered_model(name, **settings), run.loss, check_unread=False)


def test_a_loss_setting_the_models_terms_do_not_read_is_a_one_line_error_before_anything_is_made(
    tmp_path, capsys
):
    run = tmp_path / "run"
    args = ["model=lf_lstm", "loss.best_of_k_weight=1", f"run_dir={run}", f"data.root={tmp_path / 'none'}"]
    assert cli(["train", *args]) == 1
    err = capsys.readouterr().err
    assert err == (
        "mmf-rl train: error: loss.best_of_k_weight=1 is read by the 'elbo' term, which model 'lf_lstm' "
        "does not train with (its terms: ['nll']); remove it or pick loss.terms\n"
    )
    assert not run.exists()


def test_a_run_saved_with_a_loss_setting_its_model_does_not_read_still_resumes(overrides, tmp_path, capsys):
    import yaml

    assert cli(["train", *lf_lstm_overrides(overrides, "run", steps=2)]) == 0
    config = tmp_path / "run" / "config.yaml"
    saved = yaml.safe_load(config.read_text())
    saved["loss"]["kl_warmup_steps"] = 60  # as benchmarks/ethucy.py trained LF-LSTM before the check
    config.write_text(yaml.safe_dump(saved))
    unread = "loss.kl_warmup_steps=60"
    assert cli(["train", *lf_lstm_overrides(overrides, "run", steps=2), unread, "resume=true"]) == 0
    assert cli(["train", *lf_lstm_overrides(overrides, "new", steps=2), unread]) == 1
    assert "loss.kl_warmup_steps=60 is read by the 'elbo' term" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args, message",
    [
        (["trainer.lrr=1"], "Could not override 'trainer.lrr'"),
        (["model=transformer"], "Could not find 'model/transformer'"),
        (["data.root=/nonexistent/dataset"], "/nonexistent/dataset"),
        (["+loss.kl_wieght=1"], "loss config: unknown keys ['kl_wieght']"),
        (["+data.modalities.sonar.encoder=mlp"], "data config: `modalities.sonar` gives no feature"),
        (
            ["data.modalities.force={feature: observation.force, encoder: resnet}"],
            "modality 'force': encoder 'resnet' is not available; expected one of ['conv', 'conv_frames', "
            "'conv_gru', 'conv_patches', 'deepsets', 'gru',",
        ),
        (["device=cuda"] if not torch.cuda.is_available() else ["device=tpu"], "device="),
    ],
)
def test_bad_train_inputs_are_one_line_errors(overrides, args, message, capsys):
    assert cli(["train", *overrides("run"), *args]) == 1
    err = capsys.readouterr().err
    assert err.startswith("mmf-rl train: error:") and message in err and "Traceback" not in err


def test_eval_errors_for_missing_and_corrupted_checkpoints(trained, tmp_path, capsys):
    assert cli(["eval"]) == 1
    assert "checkpoint=PATH is required" in capsys.readouterr().err
    assert cli(["eval", f"checkpoint={tmp_path / 'nothing'}"]) == 1
    assert "does not exist" in capsys.readouterr().err
    run, _ = trained
    weights = load_checkpoint(run / "checkpoints").path / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])
    assert cli(["eval", f"checkpoint={run}"]) == 1
    assert "corrupted or truncated" in capsys.readouterr().err


def camera_outage_mid_episode(frames) -> None:
    """The camera dies for frames 10-12 of every episode: windows over them hold it for some steps."""
    from mmf_rl.record import CAMERA_VALID_KEY

    frames.loc[frames["frame_index"].between(10, 12), CAMERA_VALID_KEY] = False


@pytest.mark.parametrize("encoder", ["conv", "conv_frames"])
def test_training_on_partial_windows_through_a_camera_outage_has_a_finite_loss(
    recorded_push_root, tmp_path, encoder
):
    root = Path(shutil.copytree(recorded_push_root, tmp_path / "push"))
    edit_frames(root, camera_outage_mid_episode)
    run = tmp_path / "run"
    overrides = push_train_overrides(root, tmp_path / "cache", run, steps=4)
    extra = ["data.partial_windows=true", f"data.modalities.image.encoder={encoder}"]
    assert cli(["train", *overrides, *extra]) == 0
    rows = (run / "logs" / "scalars" / "train" / "loss.csv").read_text().splitlines()
    losses = torch.tensor([float(row.split(",")[-1]) for row in rows])
    assert len(losses) and torch.isfinite(losses).all()
    dataset = WindowDataset(push_data_config(root, tmp_path / "cache", partial_windows=True))
    batch = dataset.batch(torch.arange(len(dataset)))
    steps, present = batch.get(keys.present_steps_key("image")), batch.get(keys.present_key("image"))
    assert bool((present & ~steps.all(1)).any()), "some windows hold the camera for some steps only"


def small_mult_overrides(root, cache_dir, run) -> list[str]:
    base = push_train_overrides(root, cache_dir, run, steps=4)
    sizes = ["model.d_model=16", "model.head_hidden=32", "model.num_heads=2", "model.mlp_hidden=32"]
    return [*(o for o in base if not o.startswith("model.")), "model=mult", *sizes]


def logged(run: Path, name: str) -> torch.Tensor:
    rows = (run / "logs" / "scalars" / "train" / f"{name}.csv").read_text().splitlines()
    return torch.tensor([float(row.split(",")[-1]) for row in rows])


def test_mult_trains_for_missing_sensors_with_modality_dropout_and_l_mis(
    recorded_push_root, push_cache_dir, tmp_path
):
    run = tmp_path / "run"
    args = [*small_mult_overrides(recorded_push_root, push_cache_dir, run), "loss.modality_dropout=subsets"]
    assert cli(["train", *args, "loss.terms=[nll,mis]"]) == 0
    for name in ("loss_nll", "loss_mis", "dropout_fraction"):
        assert len(logged(run, name)) and torch.isfinite(logged(run, name)).all(), name
    assert 0 < float(logged(run, "dropout_fraction").mean()) < 1  # half the samples redrawn, some to all


def test_observed_modality_dropout_replays_the_recordings_own_absence_rate(
    recorded_push_root, push_cache_dir, tmp_path, capsys
):
    run = tmp_path / "complete"
    args = [*small_mult_overrides(recorded_push_root, push_cache_dir, run), "loss.modality_dropout=observed"]
    assert cli(["train", *args]) == 1
    assert "no modality is ever absent in the training split" in capsys.readouterr().err
    root = Path(shutil.copytree(recorded_push_root, tmp_path / "push"))
    edit_frames(root, camera_outage_mid_episode)  # the camera out on 3 frames of every episode
    run = tmp_path / "outage"
    edited = small_mult_overrides(root, tmp_path / "cache", run)
    assert cli(["train", *edited, "loss.modality_dropout=observed"]) == 0
    assert float(logged(run, "dropout_fraction").max()) > 0
