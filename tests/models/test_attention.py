"""The batch-first attention, the cross-modal layer's key-padding mask and MulT's pair streams
(decoder_input="pair_streams")."""

import pytest
import torch
from torch import nn

from mmf_rl.models.attention import CrossModalLayer, PairStreams, batch_first_attention, last_present_token

D = 8


def pair_streams() -> PairStreams:
    torch.manual_seed(0)
    return PairStreams([3, 1, 4], D, num_heads=2, mlp_hidden=16).eval()


def tokens_and_presence(batch: int = 4, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    tokens = torch.randn(batch, 8, D, generator=g)
    present = torch.ones(batch, 8, dtype=torch.bool)
    return tokens, present


@pytest.mark.parametrize("self_attention", [True, False])
def test_batch_first_attention_is_the_modules_own(self_attention):
    torch.manual_seed(0)
    attn = nn.MultiheadAttention(D, num_heads=2, batch_first=True)
    source = torch.randn(5, 4, D, requires_grad=True)
    query = source if self_attention else torch.randn(5, 3, D, requires_grad=True)
    hidden = torch.rand(5, 4) < 0.4
    hidden[:, 0] = False  # every row keeps a key
    inputs = [source, *attn.parameters()] + ([] if self_attention else [query])
    expected = attn(query, source, source, key_padding_mask=hidden, need_weights=False)[0]
    out = batch_first_attention(attn, query, source, hidden)
    assert torch.equal(out, expected)
    grad_out = torch.randn_like(out)
    grads = torch.autograd.grad(out, inputs, grad_out)
    for got, want in zip(grads, torch.autograd.grad(expected, inputs, grad_out), strict=True):
        torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)


def test_a_hidden_source_token_changes_nothing():
    torch.manual_seed(0)
    layer = CrossModalLayer(D, num_heads=2, mlp_hidden=16)
    query, source = torch.randn(2, 3, D), torch.randn(2, 5, D)
    hidden = torch.tensor([[False, True, False, False, True], [False] * 4 + [True]])
    changed = source.clone()
    changed[hidden] = 1e6
    with torch.no_grad():
        assert torch.equal(layer(query, source, hidden), layer(query, changed, hidden))
        assert not torch.equal(layer(query, source), layer(query, changed))


def test_pair_readouts_cover_every_ordered_pair_with_the_query_modality():
    streams = pair_streams()
    assert streams.pairs == [(i, j) for i in range(3) for j in range(3)]
    assert streams.pair_modality.tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    with torch.no_grad():
        assert streams(*tokens_and_presence()).shape == (4, 9, D)


def test_a_pair_is_absent_when_either_modality_is():
    present = torch.tensor([[True, True, True], [True, False, True]])
    pairs = pair_streams().presence(present)
    assert pairs[0].all()
    assert pairs[1].view(3, 3).tolist() == [[True, False, True], [False, False, False], [True, False, True]]


def test_alone_self_pairs_are_present_only_for_a_lone_modality():
    torch.manual_seed(0)
    streams = PairStreams([3, 1, 4], D, num_heads=2, mlp_hidden=16, self_pairs="alone")
    present = torch.tensor([[True, True, True], [True, False, True], [False, True, False]])
    pairs = streams.presence(present).view(3, 3, 3)
    assert pairs[0].tolist() == [[False, True, True], [True, False, True], [True, True, False]]
    assert pairs[1].tolist() == [[False, False, True], [False, False, False], [True, False, False]]
    assert pairs[2].tolist() == [[False, False, False], [False, True, False], [False, False, False]]


def test_the_readout_is_the_full_stream_read_at_the_last_present_query_step():
    """Modality 0 (3 tokens) loses its last step: pair (0, 2) is its stream over all its tokens, read
    at its step 1; modality 2 loses steps 0 and 3, which are hidden keys."""
    streams = pair_streams()
    tokens, present = tokens_and_presence()
    present[:, 2] = False  # modality 0's step 2
    present[:, [4, 7]] = False  # modality 2's steps 0 and 3
    with torch.no_grad():
        readouts = streams(tokens, present)
        layer = streams.layers[streams.pairs.index((0, 2))]
        full_stream = layer(tokens[:, 0:3], tokens[:, 4:8], ~present[:, 4:8])
    torch.testing.assert_close(readouts[:, 2], full_stream[:, 1])
    assert not torch.allclose(readouts[:, 2], full_stream[:, 2])


def test_values_at_absent_steps_change_no_readout():
    streams = pair_streams()
    tokens, present = tokens_and_presence()
    present[0, 2] = present[1, 5:7] = present[2, 3] = False  # a step; two steps; a whole one-token modality
    garbled = tokens.clone()
    garbled[~present] = 1e6
    with torch.no_grad():
        assert torch.equal(streams(tokens, present), streams(garbled, present))


def test_a_source_with_no_present_token_gives_a_finite_placeholder():
    streams = pair_streams()
    tokens, present = tokens_and_presence()
    present[:, 3] = False  # modality 1 absent in every row
    with torch.no_grad():
        assert bool(torch.isfinite(streams(tokens, present)).all())


def test_last_present_token_falls_back_to_the_first_without_any():
    tokens = torch.arange(6.0).view(2, 3, 1)
    present = torch.tensor([[True, True, False], [False, False, False]])
    assert last_present_token(tokens, present).flatten().tolist() == [1.0, 3.0]
