"""Action chunks for a behaviour-cloning policy, executed with temporal ensembling (ACT).

ACT (Zhao et al. 2023, "Learning Fine-Grained Bimanual Manipulation with Low-Cost Hardware")
predicts at every step a **chunk** of the next ``k`` actions instead of one, trained on the
demonstrator's next ``k`` actions (`ActionChunkLoss`; the steps past an episode's end are masked
out of the loss, never invented), and executes with **temporal ensembling**: the action sent at
step ``t`` is the weighted mean of the predictions for ``t`` of every chunk that has one (those
predicted at ``t - k + 1 .. t``), weight ``exp(-m·i)`` with ``i = 0`` for the oldest prediction.
A per-step regression averages the demonstrator's pauses and noise into each step and compounds
its errors; a chunk commits to a stretch of motion and the ensemble smooths between chunks.

`TemporalEnsemble` keeps the past chunks in the tensordict as recurrent state, the way torchrl's
`LSTMModule` keeps its hidden state: it reads them from ``PAST_CHUNKS`` and writes the updated
ones to ``("next", PAST_CHUNKS)``, forgets them where ``"is_init"`` (`InitTracker`) is set, and
`TemporalEnsemble.make_tensordict_primer` registers them in the env's specs, so a rollout carries
them from step to step and a reset (of any env of a batch) clears them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase, dispatch
from tensordict.utils import NestedKey
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.objectives import LossModule

from mmf_rl.rl.demonstrations import ACTION, DEMONSTRATED_CHUNK, DEMONSTRATED_CHUNK_MASK

ACTION_CHUNK = "action_chunk"  # ``[*B, k, A]``: a chunk policy's prediction of the next k actions
# The ensemble's recurrent state: the last k - 1 chunks, newest first, and whether each is filled
# (1.0) or empty (0.0: before the episode had that many steps). A float flag, not a bool, because
# `TensorDictPrimer` fills its entries with a float default at reset.
PAST_CHUNKS = "past_action_chunks"
PAST_CHUNKS_FILLED = "past_action_chunks_filled"
IS_INIT = "is_init"  # `InitTracker`'s key: the step is an episode's first


class TemporalEnsemble(TensorDictModuleBase):
    """ACT's temporal ensembling of a policy's action chunks, with the past chunks as recurrent state.

    Reads ``ACTION_CHUNK`` ``[*B, k, A]``, ``PAST_CHUNKS`` ``[*B, k-1, k, A]`` and
    ``PAST_CHUNKS_FILLED`` ``[*B, k-1]`` (newest first) and ``"is_init"`` ``[*B, 1]``; writes
    ``"action"`` ``[*B, A]`` and the state for the next step under ``"next"``. The chunk of age
    ``j`` (predicted ``j`` steps ago) predicts the current action at its index ``j``. ACT weighs
    the ``n`` available predictions ``exp(-m·i)``, ``i = 0`` the oldest, then normalises; that is
    ``exp(m·j)`` for age ``j`` up to a common factor, which is how it is computed here. ``decay``
    is ``m`` (ACT's 0.01: nearly a plain mean, the oldest prediction weighing slightly more).
    """

    def __init__(self, chunk: int, action_dim: int, decay: float = 0.01):
        if chunk < 2:
            raise ValueError(f"TemporalEnsemble: a chunk of {chunk} action has nothing to ensemble; k >= 2")
        if not math.isfinite(decay) or decay < 0:
            raise ValueError(f"TemporalEnsemble: decay must be finite and >= 0, found {decay}")
        super().__init__()
        self.chunk, self.action_dim, self.decay = chunk, action_dim, decay
        self.in_keys = [ACTION_CHUNK, PAST_CHUNKS, PAST_CHUNKS_FILLED, IS_INIT]
        self.out_keys = [ACTION, ("next", PAST_CHUNKS), ("next", PAST_CHUNKS_FILLED)]
        self.register_buffer("age_weights", torch.exp(decay * torch.arange(chunk)), persistent=False)

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """The env transform that holds the ensemble's state: empty chunks at every (partial) reset."""
        return TensorDictPrimer(
            {
                PAST_CHUNKS: Unbounded(shape=(self.chunk - 1, self.chunk, self.action_dim)),
                PAST_CHUNKS_FILLED: Unbounded(shape=(self.chunk - 1,)),
            },
            expand_specs=True,
        )

    def _state(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        missing = [key for key in self.in_keys[1:] if key not in tensordict.keys()]
        if missing:
            raise KeyError(
                f"TemporalEnsemble: the tensordict lacks {missing}; an action-chunk policy acts in an env "
                "with its transforms (BCPolicy.transforms(): an InitTracker and the ensemble's primer)"
            )
        kept = tensordict.get(PAST_CHUNKS_FILLED) * ~tensordict.get(IS_INIT)
        return tensordict.get(PAST_CHUNKS), kept

    @dispatch(auto_batch_size=False)
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        chunk = tensordict.get(ACTION_CHUNK)
        past, filled = self._state(tensordict)
        chunks = torch.cat([chunk.unsqueeze(-3), past], -3)  # [*B, age, step, A]
        filled = torch.cat([torch.ones_like(filled[..., :1]), filled], -1)  # [*B, age]
        now = chunks.diagonal(dim1=-3, dim2=-2).transpose(-1, -2)  # [*B, age, A]: each one's action for now
        weights = (self.age_weights * filled).unsqueeze(-1)
        tensordict.set(ACTION, (weights * now).sum(-2) / weights.sum(-2))
        tensordict.set(("next", PAST_CHUNKS), chunks[..., :-1, :, :])
        tensordict.set(("next", PAST_CHUNKS_FILLED), filled[..., :-1])
        return tensordict


class DemonstrationLoss(LossModule):
    """What a loss on the demonstrations shares (torchrl's `BCLoss` does the same for its one
    action): the actor held functionally (``actor_network_params``, what the trainer optimises),
    no value estimator, and `predict`, the actor's output on a batch under those parameters.
    Subclasses declare their ``_AcceptedKeys`` and compute ``loss_bc`` from `predict`."""

    out_keys = ["loss_bc"]

    actor_network: TensorDictModule
    actor_network_params: TensorDictParams

    def __init__(self, actor_network: TensorDictModule):
        super().__init__()
        self.convert_to_functional(actor_network, "actor_network")

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def predict(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The actor's output on (a shallow copy of) ``tensordict``, with the loss's parameters."""
        with self.actor_network_params.to_module(self.actor_network, preserve_module_state=False):
            return self.actor_network(tensordict.copy())


class ActionChunkLoss(DemonstrationLoss):
    """Mean squared error of a predicted action chunk to the demonstrated one, over the steps the
    demonstration has (the steps past its episode's end are masked out, as ACT masks them).

    Args:
        actor_network: writes the chunk (``[B, k, A]`` under ``action_chunk``) from a batch.

    Returns a TensorDict with ``loss_bc`` (the name torchrl's `BCLoss` gives its term, so the
    logs of policies with and without chunks compare).
    """

    @dataclass
    class _AcceptedKeys:
        """Keys of the batch (`DemonstrationLoader` with ``action_chunk``) and of the actor's output.

        Attributes:
            action_chunk: the chunk the actor predicts, ``[B, k, A]``.
            demonstrated_chunk: the demonstrator's next k actions, ``[B, k, A]``.
            demonstrated_chunk_mask: ``[B, k]``, whether step ``i`` of the chunk is in the episode.
        """

        action_chunk: NestedKey = ACTION_CHUNK
        demonstrated_chunk: NestedKey = DEMONSTRATED_CHUNK
        demonstrated_chunk_mask: NestedKey = DEMONSTRATED_CHUNK_MASK

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [*self.actor_network.in_keys, keys.demonstrated_chunk, keys.demonstrated_chunk_mask]

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        predicted = self.predict(tensordict).get(keys.action_chunk)
        target = tensordict.get(keys.demonstrated_chunk)
        mask = tensordict.get(keys.demonstrated_chunk_mask).unsqueeze(-1).to(predicted.dtype)
        squared = (predicted - target) ** 2 * mask
        loss = squared.sum() / (mask.sum() * predicted.shape[-1])
        return TensorDict({"loss_bc": loss})
