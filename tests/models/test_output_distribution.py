"""Every model with a scale head takes the output family through one setting (``model.output_distribution``,
``model.output_df``), saved with its config; a config saved before the option loads as ``normal``; each
family trains every model, L_mis included; the predictive mixture and the world model read the family."""

from __future__ import annotations

import math

import pytest
import torch

from mmf_rl.configuration import compose_config, to_container
from mmf_rl.models import MODELS, build_loss, build_model, model_from_saved_config, saved_config
from mmf_rl.models.forecaster.modeling_forecaster import moment_match
from mmf_rl.objectives import LossConfig, output_distribution, output_distribution_of
from tests.conftest import (
    HISTORY,
    HORIZON,
    SMALL_MODALITIES,
    TARGET_DIM,
    assert_a_few_steps_reduce_the_loss,
    make_batch,
    small_registered_model,
)

FAMILIES = {"normal": {}, "laplace": {}, "student_t": {"output_df": 3.0}}
SHIPPED_MODELS = ["forecaster", "lf_lstm", "mult", "mvae"]  # configs/model/*.yaml
# The models and terms the training smoke test runs each family with: between them every likelihood
# term (the ELBO's, L_mis's KL, nll), in the paper model and in a baseline.
TRAINED = {"forecaster": ["elbo", "mis"], "mult": ["nll", "mis"]}


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_every_registered_model_reads_and_saves_its_family(name, family):
    model = small_registered_model(name, output_distribution=family, **FAMILIES[family])
    found = output_distribution_of(model)
    assert found.settings() == output_distribution(family, **FAMILIES[family]).settings()
    assert found.name == family and model.config.output_distribution == family
    rebuilt = model_from_saved_config(saved_config(name, model))
    assert output_distribution_of(rebuilt).settings() == found.settings()


@pytest.mark.parametrize("name", sorted(MODELS))
def test_a_config_saved_before_the_option_loads_as_normal(name):
    """As an older mmf-rl saved it: without ``output_distribution`` and ``output_df``."""
    saved = saved_config(name, small_registered_model(name))
    old = {key: value for key, value in saved.items() if not key.startswith("output_")}
    assert old.keys() < saved.keys()
    rebuilt = model_from_saved_config(old)
    assert rebuilt.config.output_distribution == "normal" and output_distribution_of(rebuilt).name == "normal"


@pytest.mark.parametrize("name", SHIPPED_MODELS)
def test_the_hydra_model_group_sets_the_family_once_for_any_model(name):
    cfg = compose_config(
        "train", [f"model={name}", "model.output_distribution=student_t", "model.output_df=3"]
    )
    model = build_model(to_container(cfg.model), list(SMALL_MODALITIES), HISTORY, HORIZON, TARGET_DIM)
    assert output_distribution_of(model).describe() == "student_t (df 3)"


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"output_distribution": "cauchy"}, r"Config: unknown output distribution 'cauchy'"),
        ({"output_distribution": "student_t", "output_df": 2}, r"Config: output_df must be a number > 2"),
    ],
)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_an_unknown_family_or_a_bad_df_is_refused_when_the_config_is_made(name, setting, message):
    with pytest.raises(ValueError, match=message):
        small_registered_model(name, **setting)


@pytest.mark.parametrize("name", sorted(TRAINED))
@pytest.mark.parametrize("family", ["laplace", "student_t"])
def test_a_few_training_steps_reduce_the_loss_under_each_family(name, family):
    model = small_registered_model(name, output_distribution=family, **FAMILIES[family]).train()
    loss = build_loss(name, model, LossConfig(terms=TRAINED[name]))
    assert_a_few_steps_reduce_the_loss(model, loss)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_the_predictive_mixture_is_moment_matched_in_the_familys_variance(family):
    """``eval_latent="predictive"``: the forecast's variance (the family's ``stddev²``) is the mixture's,
    mean of the components' variances plus the variance of their means."""
    found = output_distribution(family, **FAMILIES[family])
    g = torch.Generator().manual_seed(0)
    loc, scale = torch.randn(8 * 3, 2, generator=g), torch.rand(8 * 3, 2, generator=g) + 0.5
    mixed_loc, mixed_scale = moment_match(loc, scale, 8, found.variance)
    components_loc, components_std = loc.unflatten(0, (8, 3)), found.stddev(scale).unflatten(0, (8, 3))
    torch.testing.assert_close(mixed_loc, components_loc.mean(0))
    expected = components_std.square().mean(0) + components_loc.var(0, correction=0)
    torch.testing.assert_close(found.stddev(mixed_scale).square(), expected)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_the_world_models_standard_deviation_is_the_familys(family):
    from mmf_rl.rl import WorldModel

    model = small_registered_model(
        "forecaster", output_distribution=family, action_dim=4, action_steps=HORIZON, **FAMILIES[family]
    )
    stats = {
        f"{s.name}/{k}": torch.full(s.shape, v)
        for s in SMALL_MODALITIES
        if s.kind != "image"
        for k, v in (("mean", 0.0), ("std", 1.0))
    }
    stats |= {"target/mean": torch.zeros(TARGET_DIM), "target/std": torch.full((TARGET_DIM,), 2.0)}
    stats |= {"future_action/mean": torch.zeros(4), "future_action/std": torch.ones(4)}
    world = WorldModel(model, stats)
    batch = small_batch_window()
    encoded = world.encode(batch)
    actions = torch.rand(2, 3, HORIZON, 4)
    loc, std = world.forecast_distribution(*encoded, actions)
    _, scale = world._decode(*encoded, actions)
    factor = math.sqrt(output_distribution(family, **FAMILIES[family]).variance)
    torch.testing.assert_close(std, 2.0 * factor * scale)
    # A window with no sensor: the marginal, the target's training std, whatever the family.
    torch.testing.assert_close(std[1], torch.full_like(std[1], 2.0))


def small_batch_window():
    """Two history windows as `HistoryWindow` writes them (no target), the second without any sensor."""
    absent = torch.tensor([True, False])
    return make_batch(2, present={s.name: absent for s in SMALL_MODALITIES}).exclude("target", "target_past")
