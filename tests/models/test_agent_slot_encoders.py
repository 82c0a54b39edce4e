"""The slot-order-invariant encoders of agent neighbourhoods (``deepsets``, ``set_attention``)."""

import pytest
import torch

from mmf_rl.keys import ModalitySpec
from mmf_rl.models.encoders import build_encoder

SLOTS, SLOT_DIM, HISTORY = 6, 5, 8
SLOT_ENCODERS = ("deepsets", "set_attention")


def _encoder(name: str):
    torch.manual_seed(0)
    spec = ModalitySpec("neighbours", "sequence", (SLOTS * SLOT_DIM,), encoder=name)
    return build_encoder(spec, HISTORY, 16).eval()


def _window(n: int = 4) -> torch.Tensor:
    slots = torch.randn(n, HISTORY, SLOTS, SLOT_DIM)
    slots[..., -1] = (torch.rand(n, HISTORY, SLOTS) < 0.6).float()
    slots[0, 2, :, -1] = 0.0  # a step with no neighbour at all
    return slots


@pytest.mark.parametrize("name", SLOT_ENCODERS)
def test_slot_order_does_not_matter(name):
    encoder, slots = _encoder(name), _window()
    permuted = slots[:, :, torch.randperm(SLOTS)]
    torch.testing.assert_close(encoder(slots.flatten(2)), encoder(permuted.flatten(2)))


@pytest.mark.parametrize("name", SLOT_ENCODERS)
def test_empty_slots_values_are_never_read(name):
    encoder, slots = _encoder(name), _window()
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


@pytest.mark.parametrize("name", SLOT_ENCODERS)
def test_a_feature_that_is_not_whole_slots_is_refused(name):
    spec = ModalitySpec("neighbours", "sequence", (7,), encoder=name)
    with pytest.raises(ValueError, match=f"{name} encoder .* slot_dim=5"):
        build_encoder(spec, HISTORY, 16)


def test_set_attention_reads_one_agent_among_many_and_steps_with_nobody():
    """One agent's values move the output when every slot is full, and a window whose steps have
    nobody (every key but the learned "nobody" token masked) still gives a finite output."""
    encoder = _encoder("set_attention")
    slots = _window(2)
    slots[..., -1] = 1.0
    out = encoder(slots.flatten(2))
    assert out.shape == (2, 16)
    moved = slots.clone()
    moved[:, -1, 0, :2] += 3.0
    assert (encoder(moved.flatten(2)) - out).abs().amax() > 1e-3
    slots[..., -1] = 0.0
    assert torch.isfinite(encoder(slots.flatten(2))).all()
