from dataclasses import asdict

import pytest

from mmf_rl.configuration import compose_config, config_dir, to_container
from mmf_rl.objectives import LossConfig


@pytest.mark.parametrize("option", sorted(p.stem for p in (config_dir() / "loss").glob("*.yaml")))
def test_every_loss_yaml_sets_every_field_of_the_loss_config(option):
    # The YAML is the source of a run's values: none may fall back to the dataclass default.
    values = to_container(compose_config("train", [f"loss={option}"]).loss)
    assert asdict(LossConfig.from_dict(values)) == values


def test_an_unknown_loss_key_is_a_clear_error():
    with pytest.raises(ValueError, match=r"loss config: unknown keys \['kl_wieght'\]; expected a subset of"):
        LossConfig.from_dict({"kl_wieght": 1.0})


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("kl_weight", -1.0, "loss.kl_weight must be >= 0, found -1.0"),
        ("kl_warmup_steps", -5, "loss.kl_warmup_steps must be >= 0, found -5"),
        ("missing_modality_weight", -0.5, "loss.missing_modality_weight must be >= 0"),
        ("detach_teacher", "yes", "loss.detach_teacher must be true or false, found 'yes'"),
        ("best_of_k_weight", -1.0, "loss.best_of_k_weight must be >= 0, found -1.0"),
        ("best_of_k_samples", 0, "loss.best_of_k_samples must be a whole number >= 1, found 0"),
        ("best_of_k_samples", 2.5, "loss.best_of_k_samples must be a whole number >= 1, found 2.5"),
    ],
)
def test_bad_values_name_the_key(field, value, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        LossConfig(**{field: value})


@pytest.mark.parametrize("value", [0, -1, 1.5, True, "two"])
def test_max_dropped_must_be_a_whole_number_of_at_least_one_or_null(value):
    with pytest.raises(ValueError, match="loss.max_dropped must be a whole number >= 1 or null"):
        LossConfig(max_dropped=value)
    assert LossConfig(max_dropped=None).max_dropped is None


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("step_drop_prob", 1.5, r"loss.step_drop_prob must be in \[0, 1\], found 1.5"),
        ("step_drop_prob", -0.5, r"loss.step_drop_prob must be in \[0, 1\], found -0.5"),
        ("max_dropped_steps", 0, "loss.max_dropped_steps must be a whole number >= 1 or null"),
        ("max_dropped_steps", 2.5, "loss.max_dropped_steps must be a whole number >= 1 or null"),
    ],
)
def test_bad_tail_cut_options_name_the_key(field, value, message):
    with pytest.raises(ValueError, match=message):
        LossConfig(**{field: value})
