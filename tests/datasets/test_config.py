"""Data config entries: a feature's dims are whole-number indices, or a clear error naming the setting."""

import pytest

from mmf_rl.datasets.config import ActionConfig, ModalityConfig, TargetConfig


def test_dims_are_kept_as_integer_indices():
    assert TargetConfig(feature="observation.state", dims=[0, 1.0]).dims == [0, 1]
    assert ModalityConfig(feature="observation.state", dims=None).dims is None


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: TargetConfig(feature="observation.state", dims=[0, 1.5]), "`target.dims`"),
        (
            lambda: TargetConfig(feature="s", relative_to={"feature": "g", "dims": 2}),
            "`target.relative_to.dims`",
        ),
        (lambda: ActionConfig(dims=["x"]), "`action.dims`"),
        (
            lambda: ModalityConfig(feature="observation.force", dims=[True]),
            "modality feature 'observation.force': dims",
        ),
        (lambda: ModalityConfig(feature="observation.force", raw_dims="01"), "raw_dims"),
    ],
)
def test_a_dim_that_is_not_a_whole_number_names_the_setting(make, message):
    with pytest.raises(ValueError, match="must be a list of whole-number indices") as error:
        make()
    assert message in str(error.value)
