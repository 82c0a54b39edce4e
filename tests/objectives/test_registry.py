"""The loss terms' registry: each term names the loss settings it reads, and a setting changed from its
default that none of the terms in use reads is refused instead of silently ignored."""

from __future__ import annotations

import dataclasses
import re

import pytest

from mmf_rl.configuration import ConfigError
from mmf_rl.objectives import (
    GLOBAL_LOSS_SETTINGS,
    LOSS_TERMS,
    GaussianNLLLoss,
    LossConfig,
    build_loss_terms,
    check_settings_read,
    default_loss_config,
    terms_reading,
)
from tests.conftest import small_registered_model


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
    check_settings_read(["nll", "elbo"], LossConfig(terms=["nll", "elbo"], kl_warmup_steps=5))


def test_a_setting_is_compared_with_the_defaults_given():
    # The loss config group warms the KL up, for every model: not a choice of the user's.
    shipped = default_loss_config()
    assert shipped.kl_warmup_steps != LossConfig().kl_warmup_steps
    check_settings_read(["nll"], shipped, model_name="lf_lstm", defaults=shipped)
    with pytest.raises(ConfigError, match=r"^loss\.kl_warmup_steps=\d+ is read by the 'elbo' term"):
        check_settings_read(["nll"], shipped, model_name="lf_lstm")
    changed = dataclasses.replace(shipped, kl_warmup_steps=shipped.kl_warmup_steps + 1)
    with pytest.raises(ConfigError, match=r"^loss\.kl_warmup_steps=\d+ is read by the 'elbo' term"):
        check_settings_read(["nll"], changed, model_name="lf_lstm", defaults=shipped)


def test_check_unread_false_builds_the_terms_of_a_run_as_it_was_trained():
    # A run saved before the check may hold such a setting: its loss is rebuilt all the same.
    model = small_registered_model("lf_lstm")
    loss = build_loss_terms(["nll"], model, LossConfig(kl_warmup_steps=60), check_unread=False)
    assert isinstance(loss, GaussianNLLLoss)
