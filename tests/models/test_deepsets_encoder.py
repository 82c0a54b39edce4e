"""The slot-order-invariant encoder of agent neighbourhoods (``deepsets``)."""

import pytest
import torch

from mmf_rl.keys import ModalitySpec
from mmf_rl.models.encoders import build_encoder

SLOTS, SLOT_DIM, HISTORY = 6, 5, 8


def _encoder():
    torch.manual_seed(0)
    spec = ModalitySpec("neighbours", "sequence", (SLOTS * SLOT_DIM,), encoder="deepsets")
    return build_encoder(spec, HISTORY, 16).eval()


def _window(n: int = 4) -> torch.Tensor:
    slots = torch.randn(n, HISTORY, SLOTS, SLOT_DIM)
    slots[..., -1] = (torch.rand(n, HISTORY, SLOTS) < 0.6).float()
    slots[0, 2, :, -1] = 0.0  # a step with no neighbour at all
    return slots


def test_slot_order_does_not_matter():
    encoder, slots = _encoder(), _window()
    permuted = slots[:, :, torch.randperm(SLOTS)]
    torch.testing.assert_close(encoder(slots.flatten(2)), encoder(permuted.flatten(2)))


def test_empty_slots_values_are_never_read():
    encoder, slots = _encoder(), _window()
    garbage = slots.clone()
    empty = garbage[..., -1] == 0
    garbage[..., :-1][empty] = torch.randn(int(empty.sum()), SLOT_DIM - 1) * 100
    out = encoder(slots.flatten(2))
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, encoder(garbage.flatten(2)))
    # ... while a valid slot's values are read.
    slots[..., 0, :-1] += 1.0
    slots[..., 0, -1] = 1.0
    assert not torch.allclose(out, encoder(slots.flatten(2)))


def test_a_feature_that_is_not_whole_slots_is_refused():
    spec = ModalitySpec("neighbours", "sequence", (7,), encoder="deepsets")
    with pytest.raises(ValueError, match="slot_dim=5"):
        build_encoder(spec, HISTORY, 16)
