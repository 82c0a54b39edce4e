"""ACT's temporal ensembling of action chunks and the masked chunk loss."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential

from mmf_rl.rl.action_chunks import (
    ACTION_CHUNK,
    PAST_CHUNKS,
    PAST_CHUNKS_FILLED,
    ActionChunkLoss,
    TemporalEnsemble,
)
from mmf_rl.rl.demonstrations import DEMONSTRATED_CHUNK, DEMONSTRATED_CHUNK_MASK


def act_ensemble(chunks: list[torch.Tensor], decay: float) -> list[torch.Tensor]:
    """ACT's own formula, read literally: a table of every chunk's predictions by time, then at each
    step the predictions for it, oldest first, weighted ``exp(-decay * i)`` and normalised."""
    k = chunks[0].shape[0]
    table = {}
    actions = []
    for t, chunk in enumerate(chunks):
        for i in range(k):
            table.setdefault(t + i, []).append(chunk[i])  # appended in time order: oldest first
        now = torch.stack(table[t])
        weights = torch.tensor([math.exp(-decay * i) for i in range(len(now))])
        actions.append((now * (weights / weights.sum())[:, None]).sum(0))
    return actions


def empty_state(batch: int, k: int, action_dim: int) -> TensorDict:
    """What the ensemble's primer writes at a reset."""
    return TensorDict(
        {
            PAST_CHUNKS: torch.zeros(batch, k - 1, k, action_dim),
            PAST_CHUNKS_FILLED: torch.zeros(batch, k - 1),
        },
        batch_size=[batch],
    )


def play(ensemble: TemporalEnsemble, chunks: torch.Tensor, is_init: torch.Tensor) -> torch.Tensor:
    """Step the ensemble through ``chunks`` ``[T, B, k, A]`` as a rollout does (state from
    ``"next"``); returns the actions ``[T, B, A]``."""
    state = empty_state(chunks.shape[1], ensemble.chunk, ensemble.action_dim)
    actions = []
    for t in range(len(chunks)):
        out = ensemble(state.update({ACTION_CHUNK: chunks[t], "is_init": is_init[t].unsqueeze(-1)}))
        actions.append(out.get("action"))
        state = out.get("next").clone()
    return torch.stack(actions)


def test_the_ensemble_is_acts_weighted_mean_of_every_chunks_prediction_for_now():
    k, decay = 3, 0.5  # a large decay: the weights differ enough to tell orders apart
    chunks = torch.arange(6 * k * 2, dtype=torch.float32).reshape(6, 1, k, 2) ** 1.5 / 10
    is_init = torch.zeros(6, 1, dtype=torch.bool)
    is_init[0] = True
    actions = play(TemporalEnsemble(k, 2, decay), chunks, is_init)
    expected = act_ensemble(list(chunks[:, 0]), decay)
    torch.testing.assert_close(actions[:, 0], torch.stack(expected))
    torch.testing.assert_close(actions[0, 0], chunks[0, 0, 0])  # first step: its own first action
    # Step 2 by hand: chunk 0's index 2 (oldest, weight 1), chunk 1's index 1, chunk 2's index 0.
    weights = torch.tensor([1.0, math.exp(-decay), math.exp(-2 * decay)])
    now = torch.stack([chunks[0, 0, 2], chunks[1, 0, 1], chunks[2, 0, 0]])
    torch.testing.assert_close(actions[2, 0], (weights[:, None] * now).sum(0) / weights.sum())


def test_a_reset_clears_the_past_chunks_of_that_env_only():
    k, steps = 4, 7
    chunks = torch.randn(steps, 2, k, 3, generator=torch.Generator().manual_seed(0))
    is_init = torch.zeros(steps, 2, dtype=torch.bool)
    is_init[0] = True
    is_init[3, 1] = True  # env 1 starts a new episode at step 3, env 0 goes on
    ensemble = TemporalEnsemble(k, 3)
    actions = play(ensemble, chunks, is_init)
    torch.testing.assert_close(actions[:, 0], torch.stack(act_ensemble(list(chunks[:, 0]), 0.01)))
    torch.testing.assert_close(actions[:3, 1], torch.stack(act_ensemble(list(chunks[:3, 1]), 0.01)))
    torch.testing.assert_close(actions[3:, 1], torch.stack(act_ensemble(list(chunks[3:, 1]), 0.01)))
    torch.testing.assert_close(actions[3, 1], chunks[3, 1, 0])


def test_the_ensemble_names_the_transforms_it_lacks_and_refuses_a_chunk_of_one():
    ensemble = TemporalEnsemble(2, 4)
    with pytest.raises(KeyError, match=r"InitTracker and the ensemble's primer"):
        ensemble(TensorDict({ACTION_CHUNK: torch.zeros(2, 4)}, batch_size=[]))
    with pytest.raises(ValueError, match="k >= 2"):
        TemporalEnsemble(1, 4)
    primer = ensemble.make_tensordict_primer()
    assert primer.primers[PAST_CHUNKS].shape == (1, 2, 4)
    assert primer.primers[PAST_CHUNKS_FILLED].shape == (1,)


def test_the_chunk_loss_is_the_mean_squared_error_over_the_steps_in_the_episode():
    torch.manual_seed(0)
    actor = TensorDictModule(torch.nn.Linear(5, 3 * 2), in_keys=["obs"], out_keys=[ACTION_CHUNK])
    reshape = TensorDictModule(lambda x: x.reshape(-1, 3, 2), in_keys=[ACTION_CHUNK], out_keys=[ACTION_CHUNK])
    loss = ActionChunkLoss(TensorDictSequential(actor, reshape))
    mask = torch.tensor([[True, True, True], [True, True, False], [True, False, False]])
    batch = TensorDict(
        {"obs": torch.randn(3, 5), DEMONSTRATED_CHUNK: torch.randn(3, 3, 2), DEMONSTRATED_CHUNK_MASK: mask},
        batch_size=[3],
    )
    value = loss(batch).get("loss_bc")
    predicted = actor.module(batch.get("obs")).reshape(3, 3, 2)
    expected = ((predicted - batch.get(DEMONSTRATED_CHUNK))[mask] ** 2).mean()
    torch.testing.assert_close(value, expected)
    moved = batch.clone()
    moved.get(DEMONSTRATED_CHUNK)[~mask] = 100.0  # past the episode's end: never read
    torch.testing.assert_close(loss(moved).get("loss_bc"), value)
    value.backward()
    assert actor.module.weight.grad is not None and actor.module.weight.grad.abs().sum() > 0
