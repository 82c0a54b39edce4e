"""The push-like model build: its channels-last layout (a speed-up candidate of
benchmarks/model_throughput.py) computes the same forecasts and gradients."""

from __future__ import annotations

import pytest
import torch

from benchmarks.synthetic.push_like import build_for_push, push_like_batch
from mmf_rl import keys


def forecast_and_gradients(name: str, channels_last: bool):
    torch.manual_seed(0)
    model, loss = build_for_push(name, image_size=16, channels_last=channels_last)
    batch = push_like_batch(6, image_size=16, seed=3)
    torch.manual_seed(1)  # the same latent draws and dropped modalities in both layouts
    terms = loss(batch.clone())
    sum(v for k, v in terms.items() if k.startswith("loss_")).backward()
    model.eval()
    with torch.no_grad():
        loc = model(batch.clone()).get(keys.FORECAST_LOC)
    return model, loc, {n: p.grad for n, p in model.named_parameters() if p.grad is not None}


# The stacked-frame ConvNet (forecaster, MVAE) and the per-frame one of the baselines (MulT, as LF-LSTM).
@pytest.mark.parametrize("name", ["forecaster", "mult"])
def test_channels_last_changes_the_layout_not_the_numbers(name):
    _, loc, grads = forecast_and_gradients(name, channels_last=False)
    model, loc_cl, grads_cl = forecast_and_gradients(name, channels_last=True)
    convs = [p for p in model.parameters() if p.dim() == 4]
    assert convs and all(p.is_contiguous(memory_format=torch.channels_last) for p in convs)
    torch.testing.assert_close(loc_cl, loc, rtol=1e-4, atol=1e-5)
    assert grads_cl.keys() == grads.keys()
    for n in grads:
        torch.testing.assert_close(grads_cl[n], grads[n], rtol=1e-3, atol=1e-5, msg=n)
