"""The loss terms' registry: each term names the loss settings it reads, and a setting changed from its
default that none of the terms in use reads is refused instead of silently ignored."""

from __future__ import annotations

import dataclasses
import re

import pytest
import torch

from mmf_rl.configuration import ConfigError
from mmf_rl.objectives import (
    GLOBAL_LOSS_SETTINGS,
    LOSS_TERMS,
    GaussianNLLLoss,
    LossConfig,
    build_loss_terms,
    check_settings_read,
    default_loss_config,
    model_settings_of,
    terms_reading,
)
from tests.conftest import make_batch, small_registered_model


class RecordingConfig:
    """A loss config that records the settings read from it."""

    def __init__(self, config: LossConfig):
        self.config, self.read = config, set()

    def __getattr__(self, name):
        self.read.add(name)
        return getattr(self.config, name)


@pytest.mark.parametrize("name", sorted(LOSS_TERMS))
def test_each_term_declares_exactly_the_settings_its_from_config_reads(name):
    recording = RecordingConfig(LossConfig())  # every term on: each reads all it can
    assert LOSS_TERMS[name].from_config(small_registered_model("forecaster"), recording) is not None
    assert recording.read == LOSS_TERMS[name].config_fields


def test_every_setting_but_the_choice_of_terms_is_read_by_a_registered_term():
    for field in dataclasses.fields(LossConfig):
        assert bool(terms_reading(field.name)) != (field.name in GLOBAL_LOSS_SETTINGS), field.name


@pytest.mark.parametrize(
    "terms, model, cfg, message",
    [
        (  # a setting of a term the model does not train with
            ["nll"],
            "lf_lstm",
            LossConfig(best_of_k_weight=1.0),
            "loss.best_of_k_weight=1.0 is read by the 'elbo' term, which model 'lf_lstm' does not train "
            "with (its terms: ['nll']); remove it or pick loss.terms",
        ),
        (  # settings of several such terms, each named with its reader
            ["nll"],
            "mult",
            LossConfig(kl_warmup_steps=60, max_dropped=None),
            "loss.kl_warmup_steps=60 is read by the 'elbo' term and loss.max_dropped=null by the 'mis' "
            "term, which model 'mult' does not train with (its terms: ['nll']); remove them or pick "
            "loss.terms",
        ),
        (  # a term the model has, left out by loss.terms
            ["elbo"],
            "forecaster",
            LossConfig(terms=["elbo"], step_drop_prob=0.5),
            "loss.step_drop_prob=0.5 is read by the 'mis' term, which loss.terms=['elbo'] leaves out; "
            "remove it or add such a term to loss.terms",
        ),
        (  # L_mis turned off for a model that has no L_mis
            ["elbo"],
            "mvae",
            LossConfig(missing_modality_weight=0.0),
            "loss.missing_modality_weight=0.0 is read by the 'mis' term, which model 'mvae' does not "
            "train with (its terms: ['elbo']); remove it or pick loss.terms",
        ),
    ],
)
def test_a_setting_no_term_in_use_reads_is_refused_naming_it_its_readers_and_the_terms(
    terms, model, cfg, message
):
    with pytest.raises(ConfigError, match=re.escape(message)):
        build_loss_terms(terms, small_registered_model(model), cfg)


def test_settings_the_terms_in_use_read_pass():
    mvae = small_registered_model("mvae")
    assert build_loss_terms(["elbo"], mvae, LossConfig(kl_warmup_steps=60)).kl_warmup_steps == 60
    forecaster = small_registered_model("forecaster")
    build_loss_terms(["elbo", "mis"], forecaster, LossConfig(best_of_k_weight=1.0, max_dropped=None))
    # The terms chosen by loss.terms: the settings of those terms are read.
    check_settings_read(
        ["nll", "elbo"], LossConfig(terms=["nll", "elbo"], kl_warmup_steps=5), model_settings={}
    )


def test_a_setting_is_compared_with_the_defaults_given():
    # The loss config group warms the KL up, for every model: not a choice of the user's.
    shipped = default_loss_config()
    assert shipped.kl_warmup_steps != LossConfig().kl_warmup_steps
    lf_lstm = {"model_settings": {}, "model_name": "lf_lstm"}
    check_settings_read(["nll"], shipped, **lf_lstm, defaults=shipped)
    with pytest.raises(ConfigError, match=r"^loss\.kl_warmup_steps=\d+ is read by the 'elbo' term"):
        check_settings_read(["nll"], shipped, **lf_lstm)
    changed = dataclasses.replace(shipped, kl_warmup_steps=shipped.kl_warmup_steps + 1)
    with pytest.raises(ConfigError, match=r"^loss\.kl_warmup_steps=\d+ is read by the 'elbo' term"):
        check_settings_read(["nll"], changed, **lf_lstm, defaults=shipped)


@pytest.mark.parametrize(
    "terms, model, cfg, message",
    [
        (  # the settings of a term the config turns off
            ["elbo", "mis"],
            "forecaster",
            LossConfig(
                missing_modality_weight=0.0,
                detach_teacher=True,
                max_dropped=2,
                dropped_nll_weight=1.0,
                step_drop_prob=0.3,
            ),
            "loss.detach_teacher=true, loss.max_dropped=2, loss.dropped_nll_weight=1.0, "
            "loss.step_drop_prob=0.3 are read by the 'mis' term only with loss.missing_modality_weight > 0 "
            "(found 0.0, which turns it off); set that or remove them",
        ),
        (  # the learned prior's tie, for a model with the standard prior
            ["elbo", "mis"],
            "forecaster",
            LossConfig(dropped_prior_weight=2.0),
            "loss.dropped_prior_weight=2.0 is read by the 'mis' term only with a learned prior "
            "(model.prior=learned), which this model does not have; set that or remove it",
        ),
        (  # K of a best-of-K term that is off
            ["elbo", "mis"],
            "forecaster",
            LossConfig(best_of_k_samples=5),
            "loss.best_of_k_samples=5 is read by the 'elbo' term only with loss.best_of_k_weight > 0 "
            "(found 0.0); set that or remove it",
        ),
        (  # a warm-up of a KL weighted 0
            ["elbo"],
            "mvae",
            LossConfig(kl_weight=0.0, kl_warmup_steps=60),
            "loss.kl_warmup_steps=60 is read by the 'elbo' term only with loss.kl_weight > 0 (found 0.0); "
            "set that or remove it",
        ),
        (  # the length of tail cuts never made
            ["elbo", "mis"],
            "forecaster",
            LossConfig(max_dropped_steps=2),
            "loss.max_dropped_steps=2 is read by the 'mis' term only with loss.step_drop_prob > 0 "
            "(found 0.0); set that or remove it",
        ),
        (  # a setting no term in use reads, and one read under a condition: both named
            ["nll", "mis"],
            "forecaster",
            LossConfig(terms=["nll", "mis"], missing_modality_weight=0.0, max_dropped=2, kl_weight=0.5),
            "loss.kl_weight=0.5 is read by the 'elbo' term, which loss.terms=['nll', 'mis'] leaves out; "
            "remove it or add such a term to loss.terms. loss.max_dropped=2 is read by the 'mis' term only "
            "with loss.missing_modality_weight > 0 (found 0.0, which turns it off); set that or remove it",
        ),
    ],
)
def test_a_setting_read_only_under_a_condition_the_config_or_model_leaves_off_is_refused(
    terms, model, cfg, message
):
    with pytest.raises(ConfigError, match="^" + re.escape(message) + "$"):
        build_loss_terms(terms, small_registered_model(model), cfg)


def test_the_same_settings_pass_with_their_condition_on():
    forecaster = small_registered_model("forecaster")
    on = LossConfig(
        detach_teacher=True,
        max_dropped=2,
        dropped_nll_weight=1.0,
        step_drop_prob=0.3,
        max_dropped_steps=2,
        best_of_k_weight=1.0,
        best_of_k_samples=5,
    )
    assert build_loss_terms(["elbo", "mis"], forecaster, on).losses[1].max_dropped_steps == 2
    learned = small_registered_model("forecaster", prior="learned")
    assert (
        build_loss_terms(["elbo", "mis"], learned, LossConfig(dropped_prior_weight=2.0))
        .losses[1]
        .prior_weight
        == 2.0
    )
    mvae = small_registered_model("mvae")
    assert (
        build_loss_terms(["elbo"], mvae, LossConfig(kl_weight=0.5, kl_warmup_steps=60)).kl_warmup_steps == 60
    )


def changed(value):
    """Another valid value of a loss setting."""
    if isinstance(value, bool):
        return not value
    if value is None:
        return 2
    if isinstance(value, str):  # a choice: the step cut's place
        return {"tail": "burst", "burst": "tail"}[value]
    return value + 3 if isinstance(value, int) else value + 0.5


@pytest.mark.parametrize(
    "model, settings, terms, cfg",
    [
        ("forecaster", {}, ["elbo", "mis"], LossConfig(missing_modality_weight=0.0)),
        ("forecaster", {}, ["elbo", "mis"], LossConfig(kl_weight=0.0)),
        ("forecaster", {"prior": "learned"}, ["elbo", "mis"], LossConfig(kl_weight=0.0, step_drop_prob=0.5)),
        ("mvae", {}, ["elbo"], LossConfig(kl_weight=0.0)),
    ],
)
def test_a_setting_a_term_says_it_leaves_unread_changes_nothing_it_computes(model, settings, terms, cfg):
    model = small_registered_model(model, **settings).train()
    batch = make_batch(8, seed=1)
    unread = {name: LOSS_TERMS[name].unread_settings(cfg, model_settings_of(model)) for name in terms}
    assert any(unread.values())  # each case leaves some setting unread
    for name in terms:
        assert unread[name].keys() <= LOSS_TERMS[name].config_fields, name
        for setting in unread[name]:
            results = []
            for config in (cfg, dataclasses.replace(cfg, **{setting: changed(getattr(cfg, setting))})):
                loss = LOSS_TERMS[name].from_config(model, config)
                torch.manual_seed(0)  # the same draws of z and of the dropped modalities
                results.append(None if loss is None else outputs_and_gradients(loss, batch))
            torch.testing.assert_close(*results, rtol=0, atol=0, msg=f"{name}: {setting}")


def outputs_and_gradients(loss, batch) -> tuple[dict, list]:
    """What a loss computes on ``batch``: its outputs and the gradients of their sum (e.g. a detached
    teacher changes only the latter)."""
    out = loss(batch)
    model = loss.forecaster
    model.zero_grad(set_to_none=True)
    sum(value for key, value in out.items() if key.startswith("loss_")).backward()
    return out.detach().to_dict(), [p.grad for p in model.parameters()]


def test_check_unread_false_builds_the_terms_of_a_run_as_it_was_trained():
    # A run saved before the check may hold such a setting: its loss is rebuilt all the same.
    model = small_registered_model("lf_lstm")
    loss = build_loss_terms(["nll"], model, LossConfig(kl_warmup_steps=60), check_unread=False)
    assert isinstance(loss, GaussianNLLLoss)
