"""benchmarks/step_cost.py: every variant builds what it names and the ratios come out."""

from __future__ import annotations

import sys

from tests.conftest import load_benchmark

step_cost = load_benchmark("step_cost")


def test_variants_build_the_models_they_name():
    built = {
        label: step_cost.build(*variant, image_size=16)[0] for label, variant in step_cost.VARIANTS.items()
    }
    assert built["forecaster (default)"].config.decoder_input == "mixed"
    assert built["forecaster, raw tokens (the paper)"].config.decoder_input == "tokens"
    assert built["forecaster, per-frame image tokens"].token_counts == [10, 1, 1]
    assert type(built["MulT"]).__name__ == "MulT"


def test_main_prints_one_ratio_per_model(monkeypatch, capsys):
    argv = ["step_cost.py", "--batch-size", "4", "--image-size", "16", "--steps", "1", "--rounds", "2"]
    monkeypatch.setattr(sys, "argv", argv)
    step_cost.main()
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in lines] == list(step_cost.VARIANTS)
    assert lines[-1].endswith("1.00x MulT")
