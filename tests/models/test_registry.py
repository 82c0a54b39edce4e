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
