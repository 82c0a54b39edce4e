"""The loss terms' registry: each term names the loss settings it reads."""

from __future__ import annotations

import pytest

from mmf_rl.objectives import LOSS_TERMS, LossConfig
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
