"""The per-presence-pattern scale factors every registered model holds (mmf_rl.models.scale_calibration)."""

import json
import re

import pytest
import torch
from safetensors.torch import load_file, save_file

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError, load_checkpoint, load_model_state, save_checkpoint
from mmf_rl.models import (
    MODELS,
    ForecasterConfig,
    MultimodalForecaster,
    from_pretrained,
    saved_config,
)
from mmf_rl.models.hub import check_state_dict
from mmf_rl.models.scale_calibration import LEVELS, PresenceScaleCalibration, pattern_name
from tests.conftest import (
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    make_batch,
    presence_patterns,
    small_registered_model,
)

NAMES = [s.name for s in SMALL_MODALITIES]
FACTORS = "scale_calibration.factors"
STEP_FACTORS = "scale_calibration.step_factors"
LEVEL_FACTORS = "scale_calibration.level_factors"


def every_pattern_batch():
    """One window per non-empty presence pattern of the three small modalities, and their indices."""
    patterns = presence_patterns(NAMES)
    present = {n: torch.tensor([n in p for p in patterns]) for n in NAMES}
    index = torch.tensor([sum(1 << i for i, n in enumerate(NAMES) if n in p) for p in patterns])
    return make_batch(len(patterns), present=present, seed=1), index


def eval_scale(model, batch):
    return model(batch.clone()).get(keys.FORECAST_SCALE)


def test_pattern_index_and_names_cover_every_presence_pattern():
    calibration = PresenceScaleCalibration(3, HORIZON)
    assert calibration.factors.shape == (8,) and torch.equal(calibration.factors, torch.ones(8))
    assert torch.equal(calibration.step_factors, torch.ones(8, HORIZON)) and calibration.is_identity()
    assert torch.equal(calibration.level_factors, torch.ones(8, len(LEVELS)))
    calibration.level_factors[3, 2] = 0.5
    assert calibration.has_level_curve() and not calibration.is_identity()
    assert calibration.level_curve(torch.tensor([[True, True, False]]))[0, 2] == 0.5
    calibration.reset()
    assert calibration.is_identity()
    present = torch.tensor([[a, b, c] for c in (0, 1) for b in (0, 1) for a in (0, 1)], dtype=torch.bool)
    assert calibration.pattern_index(present).tolist() == list(range(8))
    assert [pattern_name(i, NAMES) for i in (1, 2, 4, 5, 7)] == [
        "image",
        "force",
        "proprio",
        "image+proprio",
        "image+force+proprio",
    ]


@pytest.mark.parametrize("name", sorted(MODELS))
def test_each_window_gets_its_patterns_factor_in_eval_mode_only(name):
    model = small_registered_model(name)
    assert model.state_dict()[FACTORS].shape == (2 ** len(NAMES),)
    batch, index = every_pattern_batch()
    # All ones: bit-identical to the head's own scale (the calibration skipped in train mode).
    expected = eval_scale(model, batch)
    expected_loc = model(batch.clone()).get(keys.FORECAST_LOC)
    model.scale_calibration.train()
    assert torch.equal(eval_scale(model, batch), expected)
    model.scale_calibration.eval()
    factors = torch.arange(1.0, 9.0) / 4
    model.scale_calibration.factors.copy_(factors)
    scaled = eval_scale(model, batch)
    assert scaled.shape == (len(index), HORIZON, TARGET_DIM)
    assert torch.allclose(scaled, expected * factors[index].view(-1, 1, 1), rtol=1e-6)
    assert torch.equal(model(batch.clone()).get(keys.FORECAST_LOC), expected_loc)
    # The step factors refine each pattern's factor per horizon step.
    steps = torch.linspace(0.5, 2.0, HORIZON)
    model.scale_calibration.step_factors.copy_(torch.outer(torch.ones(8), steps))
    model.scale_calibration.step_factors[index[0]] = 3.0
    per_step = factors[index].view(-1, 1, 1) * model.scale_calibration.step_factors[index].unsqueeze(-1)
    assert torch.allclose(eval_scale(model, batch), expected * per_step, rtol=1e-6)
    # Training sees the head's own scale, whatever the factors (a deterministic baseline's forward
    # in train mode is its eval forward).
    if name in ("lf_lstm", "mult"):
        assert torch.equal(model.train()(batch.clone()).get(keys.FORECAST_SCALE), expected)


def test_the_forecasters_lean_and_world_model_paths_apply_the_factors(small_config):
    torch.manual_seed(0)
    model = MultimodalForecaster(small_config).eval()
    batch, index = every_pattern_batch()
    model.scale_calibration.factors.copy_(torch.arange(1.0, 9.0))
    tokens, present = model.encode(batch)
    loc, scale = model.forecast_from_tokens(tokens, present)
    out = model(batch.clone())
    assert torch.equal(loc, out.get(keys.FORECAST_LOC)) and torch.allclose(
        scale, out.get(keys.FORECAST_SCALE)
    )

    world = MultimodalForecaster(
        ForecasterConfig(**{**small_config.to_dict(), "action_steps": 5, "action_dim": 2})
    )
    world.eval().scale_calibration.factors.copy_(torch.arange(1.0, 9.0))
    actions = torch.randn(len(index), 3, 5, 2)
    _, calibrated = world.forecast_under_actions(batch, actions)
    world.scale_calibration.reset()
    _, raw = world.forecast_under_actions(batch, actions)
    assert torch.allclose(calibrated, raw * (index + 1).float().view(-1, 1, 1, 1), rtol=1e-6)


def loaded_from_old_state(name, model, old, tmp_path, stale):
    """``model`` loaded back from a checkpoint of `mmf-rl train` and from a ``save_pretrained``
    directory that hold the older state ``old``, in eval mode. The checkpoint loads into a model whose
    ``stale`` buffer (a state-dict key) is filled with 2: loading must bring it back to ones."""
    save_checkpoint(tmp_path / "ckpt", 3, old, meta={"model_config": saved_config(name, model)})
    restored = small_registered_model(name)
    restored.get_buffer(stale).fill_(2.0)
    load_model_state(restored, load_checkpoint(tmp_path / "ckpt"))
    model.save_pretrained(tmp_path / "export")
    save_file(old, tmp_path / "export" / "model.safetensors")
    return restored.eval(), from_pretrained(tmp_path / "export")


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_state_saved_before_the_factors_loads_as_ones_and_forecasts_the_same(name, tmp_path):
    model = small_registered_model(name)
    batch, _ = every_pattern_batch()
    expected = model(batch.clone())
    # What older mmf-rl saved: neither the factors nor the step factors nor the level curves.
    old = {k: v for k, v in model.state_dict().items() if k not in (FACTORS, STEP_FACTORS, LEVEL_FACTORS)}

    restored, exported = loaded_from_old_state(name, model, old, tmp_path, stale=FACTORS)
    assert FACTORS not in load_file(tmp_path / "export" / "model.safetensors")
    check_state_dict(small_registered_model(name), old, "old weights")
    for loaded in (restored, exported):
        assert loaded.scale_calibration.is_identity()
        out = loaded(batch.clone())
        for key in (keys.FORECAST_LOC, keys.FORECAST_SCALE):
            assert torch.equal(out.get(key), expected.get(key))
    # Only the factors are completed: any other missing weight stays an error naming it.
    dropped = next(iter(old))
    with pytest.raises(CheckpointError, match=re.escape(f"missing: ['{dropped}']")):
        check_state_dict(
            small_registered_model(name), {k: v for k, v in old.items() if k != dropped}, "older weights"
        )


def test_saved_factors_and_fit_record_travel_with_the_export(tmp_path):
    model = small_registered_model("lf_lstm")
    model.scale_calibration.factors.copy_(torch.linspace(1, 2, 8))
    model.calibration = {"split": "val", "factors": model.scale_calibration.factors.tolist()}
    model.save_pretrained(tmp_path / "export")
    loaded = from_pretrained(tmp_path / "export")
    assert torch.equal(loaded.scale_calibration.factors, model.scale_calibration.factors)
    assert loaded.calibration == model.calibration
    assert json.loads((tmp_path / "export" / "calibration.json").read_text())["split"] == "val"
    # A model without a fit written over the export removes the stale record.
    small_registered_model("lf_lstm").save_pretrained(tmp_path / "export")
    assert not (tmp_path / "export" / "calibration.json").exists()
    assert from_pretrained(tmp_path / "export").calibration is None


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_state_with_per_pattern_factors_only_loads_them_with_step_factors_of_ones(name, tmp_path):
    """What a model calibrated before the step factors existed saved: its factors, applied as fitted."""
    model = small_registered_model(name)
    model.scale_calibration.factors.copy_(torch.linspace(0.5, 2.0, 8))
    batch, _ = every_pattern_batch()
    expected = eval_scale(model, batch)
    old = {k: v for k, v in model.state_dict().items() if k not in (STEP_FACTORS, LEVEL_FACTORS)}
    for loaded in loaded_from_old_state(name, model, old, tmp_path, stale=STEP_FACTORS):
        assert torch.equal(loaded.scale_calibration.factors, model.scale_calibration.factors)
        assert torch.equal(loaded.scale_calibration.step_factors, torch.ones(8, HORIZON))
        assert not loaded.scale_calibration.has_level_curve()
        assert torch.equal(eval_scale(loaded, batch), expected)


@pytest.mark.parametrize("name", ["forecaster", "lf_lstm"])
def test_a_state_saved_before_the_level_curves_loads_them_as_the_familys_own(name, tmp_path):
    """What a model calibrated before the level curves existed saved: its factors and step factors,
    applied as fitted, and the family's own intervals (curves of ones)."""
    model = small_registered_model(name)
    model.scale_calibration.factors.copy_(torch.linspace(0.5, 2.0, 8))
    model.scale_calibration.step_factors.copy_(torch.linspace(0.8, 1.2, HORIZON).expand(8, -1))
    batch, _ = every_pattern_batch()
    expected = eval_scale(model, batch)
    old = {k: v for k, v in model.state_dict().items() if k != LEVEL_FACTORS}
    for loaded in loaded_from_old_state(name, model, old, tmp_path, stale=LEVEL_FACTORS):
        assert torch.equal(loaded.scale_calibration.step_factors, model.scale_calibration.step_factors)
        assert torch.equal(loaded.scale_calibration.level_factors, torch.ones(8, len(LEVELS)))
        assert not loaded.scale_calibration.has_level_curve()
        assert torch.equal(eval_scale(loaded, batch), expected)
    # A fitted curve travels with the weights, and leaves the forecast's (loc, scale) alone.
    model.scale_calibration.level_factors.copy_(torch.linspace(0.6, 1.4, len(LEVELS)).expand(8, -1))
    model.save_pretrained(tmp_path / "curved")
    curved = from_pretrained(tmp_path / "curved")
    assert torch.equal(curved.scale_calibration.level_factors, model.scale_calibration.level_factors)
    assert torch.equal(eval_scale(curved, batch), expected)
