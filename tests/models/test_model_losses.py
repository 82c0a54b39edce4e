"""Each model's loss as its registered terms assemble it equals the loss of the explicit classes."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from mmf_rl.configuration import ConfigError
from mmf_rl.models import MODELS, build_loss, check_loss_settings, loss_settings_read, register_model
from mmf_rl.objectives import (
    GLOBAL_LOSS_SETTINGS,
    LOSS_TERMS,
    CombinedLoss,
    ELBOLoss,
    GaussianNLLLoss,
    LossConfig,
    MissingModalityLoss,
    register_loss_term,
)
from tests.conftest import make_batch, small_registered_model

LOSS_CONFIGS = {
    "default": LossConfig(),
    "no_mis": LossConfig(missing_modality_weight=0.0),
    "every_option": LossConfig(
        kl_weight=0.5,
        kl_warmup_steps=10,
        missing_modality_weight=2.0,
        detach_teacher=False,
        gsnn_weight=0.5,
        best_of_k_weight=0.5,
        best_of_k_samples=3,
        max_dropped=None,
        dropped_nll_weight=0.5,
        dropped_prior_weight=2.0,
    ),
}


def explicit_loss(name: str, model, cfg: LossConfig):
    """The loss of model ``name`` written out with the loss classes."""
    if name == "forecaster":
        losses = [
            ELBOLoss(
                model,
                kl_weight=cfg.kl_weight,
                kl_warmup_steps=cfg.kl_warmup_steps,
                gsnn_weight=cfg.gsnn_weight,
                best_of_k_weight=cfg.best_of_k_weight,
                best_of_k_samples=cfg.best_of_k_samples,
            )
        ]
        if cfg.missing_modality_weight > 0:
            losses.append(
                MissingModalityLoss(
                    model,
                    weight=cfg.missing_modality_weight,
                    detach_teacher=cfg.detach_teacher,
                    max_dropped=cfg.max_dropped,
                    dropped_nll_weight=cfg.dropped_nll_weight,
                    prior_weight=cfg.dropped_prior_weight,
                )
            )
        return CombinedLoss(*losses)
    if name == "mvae":
        return ELBOLoss(model, kl_weight=cfg.kl_weight, kl_warmup_steps=cfg.kl_warmup_steps)
    return GaussianNLLLoss(model)


def settings_read_by(name: str, cfg: LossConfig) -> LossConfig:
    """``cfg`` with the settings that the loss of model ``name`` does not read at their defaults (the
    others are refused)."""
    read = loss_settings_read({"name": name}, cfg)
    unread = {
        field.name: getattr(LossConfig(), field.name)
        for field in dataclasses.fields(LossConfig)
        if field.name not in GLOBAL_LOSS_SETTINGS and field.name not in read
    }
    return dataclasses.replace(cfg, **unread)


@pytest.mark.parametrize("option", sorted(LOSS_CONFIGS))
@pytest.mark.parametrize("name", ["forecaster", "lf_lstm", "mvae", "mult"])
def test_the_assembled_loss_gives_the_explicit_values(name, option):
    cfg = LOSS_CONFIGS[option]
    if name == "mvae":  # it refuses the GSNN and best-of-K terms (tested in test_baselines, test_elbo)
        cfg = dataclasses.replace(cfg, gsnn_weight=0.0, best_of_k_weight=0.0)
    cfg = settings_read_by(name, cfg)
    model = small_registered_model(name).train()
    batch = make_batch(8, seed=2)
    results = []
    for loss in (build_loss(name, model, cfg), explicit_loss(name, model, cfg)):
        torch.manual_seed(0)  # the same z draws and dropped modalities for both
        results.append((type(loss), list(loss.state_dict()), loss(batch)))
    (built_type, built_state, built), (expected_type, expected_state, expected) = results
    assert built_type is expected_type and built_state == expected_state  # checkpoints keep their names
    assert set(built.keys()) == set(expected.keys())
    for key in expected.keys():
        torch.testing.assert_close(built[key], expected[key], rtol=0, atol=0, msg=key)


def test_an_unknown_model_or_loss_term_names_the_registered_ones_and_the_decorator():
    model = small_registered_model("lf_lstm")
    with pytest.raises(
        ValueError, match=r"unknown model 'lstm'; expected one of \[.*'lf_lstm'.*@register_model"
    ):
        build_loss("lstm", model, LossConfig())
    with pytest.raises(
        ValueError,
        match=r"unknown loss term 'smooth'; registered: \['elbo', 'mis', 'nll'\].*@register_loss_term",
    ):
        build_loss("lf_lstm", model, LossConfig(terms=["nll", "smooth"]))


def test_a_name_is_registered_once():
    with pytest.raises(ValueError, match="loss term 'nll' is already registered \\(GaussianNLLLoss\\)"):
        register_loss_term("nll")(ELBOLoss)
    with pytest.raises(ValueError, match="model 'mvae' is already registered \\(MVAE\\)"):
        register_model("mvae", MODELS["lf_lstm"].config_cls, loss=("nll",))(MODELS["lf_lstm"].model_cls)
    assert LOSS_TERMS["nll"] is GaussianNLLLoss


def test_loss_terms_is_a_list_of_names_or_null():
    with pytest.raises(ValueError, match="loss.terms must be a non-empty list of loss term names or null"):
        LossConfig(terms="nll")
    model = small_registered_model("forecaster")
    assert isinstance(build_loss("forecaster", model, LossConfig(terms=["elbo"])), ELBOLoss)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_registered_model_builds_its_loss_from_the_default_settings(name):
    build_loss(name, small_registered_model(name), LossConfig())


def test_a_setting_the_models_terms_do_not_read_is_refused_before_the_model_is_built():
    with pytest.raises(
        ConfigError, match=r"^loss\.gsnn_weight=0\.5 is read by the 'elbo' term, which model "
    ):
        check_loss_settings({"name": "mult"}, LossConfig(gsnn_weight=0.5))
    check_loss_settings({"name": "mvae"}, LossConfig(kl_warmup_steps=7))
    check_loss_settings(
        {"name": "mult"}, LossConfig(terms=["nll", "elbo"], gsnn_weight=0.5)
    )  # the terms chosen


def test_the_model_config_group_says_whether_its_model_reads_the_learned_priors_settings():
    tie = LossConfig(dropped_prior_weight=2.0)
    check_loss_settings({"name": "forecaster", "prior": "learned"}, tie)
    assert "dropped_prior_weight" in loss_settings_read({"name": "forecaster", "prior": "learned"}, tie)
    for group in ({"name": "forecaster"}, {"name": "forecaster", "prior": "standard"}, {}):  # the default's
        with pytest.raises(
            ConfigError,
            match=r"^loss\.dropped_prior_weight=2\.0 is read by the 'mis' term only with a learned",
        ):
            check_loss_settings(group, tie)
