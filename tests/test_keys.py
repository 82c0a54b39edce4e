import pytest
import torch

from mmf_rl import keys
from mmf_rl.keys import ModalitySpec, validate_batch
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, TARGET_DIM, make_batch


def test_spec_defaults_encoder_by_kind():
    assert ModalitySpec("cam", "image", (3, 8, 8)).encoder == "conv"
    assert ModalitySpec("f", "sequence", (6,)).encoder == "mlp"
    assert ModalitySpec("g", "vector", (3,)).encoder == "mlp"


@pytest.mark.parametrize(
    "kwargs, fragment",
    [
        (dict(name="x", kind="audio", shape=(3,)), "unknown kind 'audio'"),
        (
            dict(name="x", kind="image", shape=(3, 8)),
            "shape must have 3 positive dims ((C, h, w)), found (3, 8)",
        ),
        (dict(name="x", kind="sequence", shape=(0,)), "found (0,)"),
    ],
)
def test_spec_rejects_bad_definitions(kwargs, fragment):
    with pytest.raises(ValueError) as err:
        ModalitySpec(**kwargs)
    assert fragment in str(err.value)


def test_spec_roundtrips_through_dict():
    spec = ModalitySpec(
        "cam", "image", (3, 16, 16), encoder="conv_gru", required=True, encoder_kwargs={"channels": [8]}
    )
    assert ModalitySpec.from_dict(spec.to_dict()) == spec


def assert_identical(td, expected):
    torch.testing.assert_close(td.to_dict(), expected.to_dict(), rtol=0, atol=0, equal_nan=True)


def test_validate_accepts_contract_batch_and_leaves_it_unchanged(mixed_batch):
    before = mixed_batch.clone()
    validate_batch(mixed_batch, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM, require_target=True)
    assert_identical(mixed_batch, before)


def test_nonfinite_absent_is_checked_by_validate_and_applied_by_mark_nonfinite_absent(batch):
    batch[keys.obs_key("force")][[1, 5], 0, 0] = float("nan")
    before = batch.clone()
    with pytest.raises(ValueError, match=r"holds NaN or Inf in 2 sample\(s\).*batch indices \[1, 5\]"):
        validate_batch(batch, SMALL_MODALITIES, HISTORY)
    validate_batch(batch, SMALL_MODALITIES, HISTORY, nonfinite="absent")
    assert_identical(batch, before)
    keys.mark_nonfinite_absent(batch, SMALL_MODALITIES)
    assert batch[keys.present_key("force")].tolist() == [True, False, True, True, True, False, True, True]
    assert_identical(batch.exclude(keys.present_key("force")), before.exclude(keys.present_key("force")))


def test_validate_names_missing_key(batch):
    del batch[keys.present_key("force")]
    with pytest.raises(KeyError, match=r"\('present', 'force'\)"):
        validate_batch(batch, SMALL_MODALITIES, HISTORY)


@pytest.mark.parametrize(
    "key, value, expected, found",
    [
        (
            keys.obs_key("image"),
            torch.zeros(8, HISTORY, 3, 16, 16),
            "uint8 [8, 4, 3, 16, 16]",
            "float32 [8, 4, 3, 16, 16]",
        ),
        (keys.obs_key("force"), torch.zeros(8, HISTORY + 1, 6), "float32 [8, 4, 6]", "float32 [8, 5, 6]"),
        (
            keys.obs_key("force"),
            torch.zeros(8, HISTORY, 6, dtype=torch.float64),
            "float32 [8, 4, 6]",
            "float64 [8, 4, 6]",
        ),
        (keys.present_key("proprio"), torch.ones(8), "bool [8]", "float32 [8]"),
        (keys.TARGET, torch.zeros(8, HORIZON, 3), "float [8, 5, 2]", "float32 [8, 5, 3]"),
    ],
)
def test_validate_names_key_expected_and_found(batch, key, value, expected, found):
    batch.set(key, value)
    with pytest.raises(ValueError) as err:
        validate_batch(batch, SMALL_MODALITIES, HISTORY, HORIZON, TARGET_DIM)
    message = str(err.value)
    assert str(key) in message and expected in message and found in message


def test_validate_rejects_sample_without_modalities():
    present = {s.name: torch.tensor([True, False, True]) for s in SMALL_MODALITIES}
    batch = make_batch(3, present=present)
    with pytest.raises(ValueError, match=r"1 sample\(s\) have no present modality \(batch indices \[1\]\)"):
        validate_batch(batch, SMALL_MODALITIES, HISTORY)
