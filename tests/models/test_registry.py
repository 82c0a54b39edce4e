"""Saved model configs with overrides of their settings (an eval's latent), for checkpoints and exports."""

import json
from pathlib import Path

import pytest
import torch

from mmf_rl import keys
from mmf_rl.configuration import ConfigError
from mmf_rl.models import build_model, from_pretrained, model_config_with_overrides, saved_config
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, TARGET_DIM, make_batch

SMALL = {"d_model": 16, "d_latent": 4, "num_heads": 2, "mlp_hidden": 32, "head_hidden": 32}


def test_latent_override_of_a_baseline_names_the_model():
    """A baseline without the setting refuses it by name; the MVAE takes the eval latents it has."""
    checkpoint = Path("runs/x/checkpoints/step_6")
    saved = {
        name: saved_config(name, build_model({"name": name}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM))
        for name in ("lf_lstm", "mvae")
    }
    with pytest.raises(
        ConfigError,
        match=r"eval_latent=predictive: the 'lf_lstm' model of runs/x.* no setting eval_latent; remove it "
        r"\(models that have it: forecaster, mvae\)",
    ):
        model_config_with_overrides(saved["lf_lstm"], {"eval_latent": "predictive"}, checkpoint)
    with pytest.raises(
        ConfigError, match=r"the 'mvae' model of .* no setting predictive_samples; .*have it: forecaster\)"
    ):
        model_config_with_overrides(saved["mvae"], {"predictive_samples": 8}, checkpoint)
    with pytest.raises(ConfigError, match="'mvae' model .*MVAEConfig.eval_latent must be 'mean' or 'sample'"):
        model_config_with_overrides(saved["mvae"], {"eval_latent": "predictive"}, checkpoint)
    sample = model_config_with_overrides(saved["mvae"], {"eval_latent": "sample"}, checkpoint)
    assert sample == {**saved["mvae"], "eval_latent": "sample"}
    assert model_config_with_overrides(saved["lf_lstm"], {}, checkpoint) == saved["lf_lstm"]


def test_from_pretrained_builds_the_saved_model_with_the_overrides(tmp_path):
    torch.manual_seed(0)
    model = build_model({"name": "forecaster", **SMALL}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM)
    model.save_pretrained(tmp_path / "saved")
    overrides = {"eval_latent": "predictive", "predictive_samples": 4}
    loaded = from_pretrained(tmp_path / "saved", config_overrides=overrides)
    assert (loaded.config.eval_latent, loaded.config.predictive_samples) == ("predictive", 4)
    # The same weights, decoded as a model built with the setting decodes them.
    expected = build_model(
        {"name": "forecaster", **SMALL, **overrides}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM
    )
    expected.load_state_dict(model.state_dict())
    batch = make_batch(6, present={"image": torch.tensor([True, False] * 3)}, seed=4)
    forecasts = [m.eval()(batch.clone()).get(keys.FORECAST_SCALE) for m in (loaded, expected)]
    assert torch.equal(*forecasts)
    assert not torch.equal(forecasts[0], model.eval()(batch.clone()).get(keys.FORECAST_SCALE))
    assert json.loads((tmp_path / "saved" / "config.json").read_text())["eval_latent"] == "mean"
    with pytest.raises(ConfigError, match=r"predictive_samples=3 for the 'forecaster' model of .*saved: "):
        from_pretrained(tmp_path / "saved", config_overrides={"predictive_samples": 3})


def test_a_fresh_model_config_builds_the_defaults_of_the_config_and_of_mmf_rl_train():
    from mmf_rl.configuration import compose_config, to_container
    from mmf_rl.models import ForecasterConfig

    fresh = build_model({"name": "forecaster"}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM).config
    sizes = {"modalities": SMALL_MODALITIES, "history": HISTORY, "horizon": HORIZON, "target_dim": TARGET_DIM}
    assert fresh == ForecasterConfig(**sizes) and fresh.decoder_input == "mixed"
    trained = build_model(
        to_container(compose_config("train", []).model), SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM
    ).config
    assert trained == fresh


def saved_model_and_copies(tmp_path, model, drop: tuple[str, ...] = ()):
    """``model`` saved as a `mmf-rl train` checkpoint and by ``save_pretrained``, its saved config
    without the settings ``drop`` (what an older mmf-rl wrote)."""
    from mmf_rl.checkpoint import save_checkpoint

    model.normalization_stats = {"target/mean": torch.zeros(TARGET_DIM), "target/std": torch.ones(TARGET_DIM)}
    model.data_config = {"root": "data/push"}
    config = {k: v for k, v in saved_config("forecaster", model).items() if k not in drop}
    save_checkpoint(
        tmp_path / "checkpoints",
        6,
        model.state_dict(),
        meta={"model_config": config, "config": {"data": model.data_config}},
        tensors=model.normalization_stats,
    )
    model.save_pretrained(tmp_path / "export")
    (tmp_path / "export" / "config.json").write_text(json.dumps(config))
    return tmp_path / "checkpoints", tmp_path / "export"


def forecasts_of(model, batch):
    out = model.eval()(batch.clone())
    return out.get(keys.FORECAST_LOC), out.get(keys.FORECAST_SCALE)


def test_a_model_saved_before_decoder_input_loads_with_the_raw_token_decoder_it_was_trained_with(tmp_path):
    from mmf_rl.models import load_trained_model

    torch.manual_seed(0)
    old = build_model(
        {"name": "forecaster", "decoder_input": "tokens", **SMALL},
        SMALL_MODALITIES,
        HISTORY,
        HORIZON,
        TARGET_DIM,
    )
    batch = make_batch(6, present={"image": torch.tensor([True, False] * 3)}, seed=4)
    expected = forecasts_of(old, batch)
    # The same weights fit the mixed decoder, which forecasts otherwise: loading as today's default
    # would go unnoticed.
    mixed = build_model({"name": "forecaster", **SMALL}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM)
    mixed.load_state_dict(old.state_dict())
    assert not torch.equal(forecasts_of(mixed, batch)[0], expected[0])
    for saved in saved_model_and_copies(tmp_path, old, drop=("decoder_input",)):
        loaded, _, _ = load_trained_model(saved, config_overrides={"eval_latent": "mean"})
        assert loaded.config.decoder_input == "tokens", saved
        for got, want in zip(forecasts_of(loaded, batch), expected, strict=True):
            assert torch.equal(got, want)


def test_a_model_saved_now_round_trips_with_its_decoder(tmp_path):
    from mmf_rl.models import load_trained_model

    torch.manual_seed(0)
    model = build_model({"name": "forecaster", **SMALL}, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM)
    batch = make_batch(6, present={"image": torch.tensor([True, False] * 3)}, seed=4)
    expected = forecasts_of(model, batch)
    for saved in saved_model_and_copies(tmp_path, model):
        loaded, _, _ = load_trained_model(saved)
        assert loaded.config == model.config and loaded.config.decoder_input == "mixed", saved
        for got, want in zip(forecasts_of(loaded, batch), expected, strict=True):
            assert torch.equal(got, want)
