"""The README's "Extend it" examples run as written: a fusion, a model and a loss term, each used by name."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from mmf_rl.models import MODELS, build_loss, build_model
from mmf_rl.models.fusion import FUSIONS
from mmf_rl.objectives import LOSS_TERMS, LossConfig
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, SMALL_MODEL_SIZES, TARGET_DIM, make_batch

README = Path(__file__).resolve().parents[1] / "README.md"
SEQUENCES = [spec for spec in SMALL_MODALITIES if spec.kind == "sequence"]


def extend_examples() -> list[str]:
    """The README's "Extend it" python blocks, in order: fusion, model, loss term."""
    section = README.read_text().split("## Extend it\n", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


@pytest.fixture
def run_example():
    """Exec a README block; what it registers is removed afterwards, so other tests see the built-ins."""
    registries = [MODELS, FUSIONS, LOSS_TERMS]
    before = [dict(registry) for registry in registries]

    def run(index: int) -> dict:
        namespace: dict = {}
        exec(
            compile(extend_examples()[index], f"README.md (Extend it, example {index + 1})", "exec"),
            namespace,
        )
        return namespace

    yield run
    for registry, saved in zip(registries, before, strict=True):
        registry.clear()
        registry.update(saved)


def test_the_readme_has_the_three_examples():
    assert len(extend_examples()) == 3


def test_a_new_fusion_is_selected_by_model_fusion(run_example):
    run_example(0)
    torch.manual_seed(0)
    sizes = {**SMALL_MODEL_SIZES["forecaster"], "fusion": "first_token"}
    model = build_model({"name": "forecaster", **sizes}, SEQUENCES, HISTORY, HORIZON, TARGET_DIM)
    batch = make_batch(4, modalities=SEQUENCES)
    batch["present", SEQUENCES[0].name][:2] = False
    terms = build_loss("forecaster", model, LossConfig())(batch)
    assert {"loss_nll", "loss_kl", "loss_mis"} <= set(terms.keys())
    assert all(torch.isfinite(v).all() for v in terms.values())


def test_a_new_model_is_built_and_trained_by_name(run_example):
    run_example(1)
    torch.manual_seed(0)
    model = build_model({"name": "last_value"}, SEQUENCES, HISTORY, HORIZON, TARGET_DIM)
    assert type(model).__name__ == "LastValue" and model.model_name == "last_value"
    terms = build_loss("last_value", model, LossConfig())(make_batch(4, modalities=SEQUENCES))
    assert list(terms.keys()) == ["loss_nll"]
    terms["loss_nll"].backward()


def test_a_new_loss_term_is_selected_by_loss_terms(run_example):
    namespace = run_example(2)
    torch.manual_seed(0)
    model = build_model(
        {"name": "lf_lstm", **SMALL_MODEL_SIZES["lf_lstm"]}, SEQUENCES, HISTORY, HORIZON, TARGET_DIM
    )
    loss = build_loss("lf_lstm", model, LossConfig(terms=["nll", "smooth"]))
    assert isinstance(loss.losses[1], namespace["SmoothnessLoss"])
    terms = loss(make_batch(4, modalities=SEQUENCES))
    assert {"loss_nll", "loss_smooth"} == set(terms.keys())
    assert terms["loss_smooth"] > 0
