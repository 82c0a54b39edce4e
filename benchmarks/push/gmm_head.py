"""A Gaussian-mixture action head for a behaviour-cloning policy (robomimic's BC-GMM): `GMMPolicy`,
``benchmarks/bc_push.py --action-head gmm``. Measured not to help on push (0% success where the
regression head's reached 56%: docs/results.md, "A Gaussian-mixture head instead"), so it lives
with that experiment.

Where the demonstrations hold several actions for similar states (the recording's pusher pauses
and holds still after a push, so "move" and "stay" both label the same kind of state), a
mean-squared regression learns their average, a shrunken action that can stop the robot. A
mixture head (Mandlekar et al. 2021, "What Matters in Learning from Offline Human
Demonstrations for Robot Manipulation") predicts, per action step, ``C`` diagonal Gaussians over
the action dims and their weights, is trained by the negative log-likelihood of the demonstrated
action (`GMMActionLoss`), and acts with one mode instead of the average (`most_likely_mean`).

With action chunks (k > 1) there is one mixture per step of the chunk (over that step's action
dims), not one over the whole chunk: the loss then masks the steps past the episode's end per
step, exactly as `ActionChunkLoss` does, and each step's mode is chosen on its own; the chunk of modes
then goes through the policy's temporal ensemble.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, dispatch
from tensordict.utils import NestedKey
from torch import distributions as D

from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.rl.action_chunks import ACTION_CHUNK, DemonstrationLoss
from mmf_rl.rl.bc import BCConfig, BCNetwork, BCPolicy
from mmf_rl.rl.demonstrations import ACTION, DEMONSTRATED_CHUNK, DEMONSTRATED_CHUNK_MASK

# The mixture's parameters: means ``[*B, (k,) C, A]`` in the action box, scales of the same shape,
# and the components' logits ``[*B, (k,) C]`` (the chunk dim k only for a chunk policy).
GMM_LOC = ("action_gmm", "loc")
GMM_SCALE = ("action_gmm", "scale")
GMM_LOGITS = ("action_gmm", "logits")
GMM_KEYS = [GMM_LOC, GMM_SCALE, GMM_LOGITS]
# The smallest scale a component may have. The recording holds exact values many times (pauses
# are exact zeros, saturated commands are exactly +-1): a component centred on one of them could
# shrink its scale without bound and send the likelihood to infinity; the floor keeps it finite.
SCALE_FLOOR = 1e-4


def gmm_parameters(raw: torch.Tensor, components: int, action_dim: int):
    """The mixture's ``(loc, scale, logits)`` from a head's raw output ``[..., C * (2A + 1)]``:
    means squashed to the action box ``[-1, 1]`` by ``tanh`` (as the mean-squared head's action),
    scales by ``softplus`` plus `SCALE_FLOOR`, logits as they are."""
    shape = (*raw.shape[:-1], components, action_dim)
    loc, scale, logits = raw.split([components * action_dim, components * action_dim, components], -1)
    scale = torch.nn.functional.softplus(scale.reshape(shape)) + SCALE_FLOOR
    return torch.tanh(loc.reshape(shape)), scale, logits


def gmm_distribution(loc: torch.Tensor, scale: torch.Tensor, logits: torch.Tensor) -> D.MixtureSameFamily:
    """The mixture over the last dim of ``loc``/``scale`` (the action), components on the dim before."""
    return D.MixtureSameFamily(D.Categorical(logits=logits), D.Independent(D.Normal(loc, scale), 1))


def most_likely_mean(loc: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """The mean of the most likely component: ``[..., A]`` from ``loc [..., C, A]``, ``logits
    [..., C]``. Deterministic, where robomimic's low-noise evaluation samples the component: a
    policy's evaluation stays reproducible, and it still acts on one mode, never their average."""
    best = logits.argmax(-1, keepdim=True).unsqueeze(-1).expand(*loc.shape[:-2], 1, loc.shape[-1])
    return loc.gather(-2, best).squeeze(-2)


class GMMActionLoss(DemonstrationLoss):
    """Mean negative log-likelihood of the demonstrated action under the policy's mixture.

    Args:
        actor_network: writes the mixture's parameters (`GMM_KEYS`) from a batch.
        chunked: the actor predicts a chunk (``[B, k, C, A]``): the targets are the demonstrated
            chunk, its steps past the episode's end masked out as `ActionChunkLoss` masks them;
            otherwise (``[B, C, A]``) the demonstrated action.

    Returns a TensorDict with ``loss_bc`` (the name torchrl's `BCLoss` gives its term, so the logs
    of policies with either head compare; the values do not: a log-likelihood, not a squared error).
    """

    @dataclass
    class _AcceptedKeys:
        """Keys of the actor's output and of the batch (`DemonstrationLoader`).

        Attributes:
            gmm_loc, gmm_scale, gmm_logits: the mixture the actor predicts (`GMM_KEYS`).
            action: the demonstrated action ``[B, A]`` (a per-step policy's target).
            demonstrated_chunk: the demonstrator's next k actions ``[B, k, A]`` (a chunk policy's).
            demonstrated_chunk_mask: ``[B, k]``, whether step ``i`` of the chunk is in the episode.
        """

        gmm_loc: NestedKey = GMM_LOC
        gmm_scale: NestedKey = GMM_SCALE
        gmm_logits: NestedKey = GMM_LOGITS
        action: NestedKey = ACTION
        demonstrated_chunk: NestedKey = DEMONSTRATED_CHUNK
        demonstrated_chunk_mask: NestedKey = DEMONSTRATED_CHUNK_MASK

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(self, actor_network: TensorDictModule, chunked: bool = False):
        super().__init__(actor_network)
        self.chunked = chunked

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        targets = [keys.demonstrated_chunk, keys.demonstrated_chunk_mask] if self.chunked else [keys.action]
        return [*self.actor_network.in_keys, *targets]

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        predicted = self.predict(tensordict)
        mixture = gmm_distribution(
            predicted.get(keys.gmm_loc), predicted.get(keys.gmm_scale), predicted.get(keys.gmm_logits)
        )
        if not self.chunked:
            return TensorDict({"loss_bc": -mixture.log_prob(tensordict.get(keys.action)).mean()})
        log_likelihood = mixture.log_prob(tensordict.get(keys.demonstrated_chunk))  # [B, k]
        mask = tensordict.get(keys.demonstrated_chunk_mask).to(log_likelihood.dtype)
        return TensorDict({"loss_bc": -(log_likelihood * mask).sum() / mask.sum()})


@dataclass
class GMMConfig(BCConfig):
    """A `BCConfig` with ``gmm_components`` Gaussians per action step. Its dict names the head
    (``action_head: "gmm"``), as the package's config did when it had the choice: checkpoints of
    either time load."""

    gmm_components: int = 5

    def __post_init__(self):
        super().__post_init__()
        if self.gmm_components < 1:
            raise ValueError(f"GMMConfig: gmm_components must be >= 1, found {self.gmm_components}")

    def to_dict(self) -> dict:
        return {**super().to_dict(), "action_head": "gmm", "gmm_components": self.gmm_components}

    @classmethod
    def from_dict(cls, d: dict) -> GMMConfig:
        d = dict(d)
        head = d.pop("action_head", None)
        if head != "gmm":
            raise ValueError(
                f"GMMConfig: the config is of a policy with the {head or 'mse'!r} head, not a mixture; "
                "load it with BCPolicy"
            )
        reject_unknown_keys(cls, d, "BC mixture policy config")
        return cls(**d)


class GMMNetwork(BCNetwork):
    """`BCNetwork` whose head writes the mixture's ``(loc, scale, logits)`` (`gmm_parameters`), with a
    chunk dim k after ``*B`` for a chunk policy."""

    def __init__(self, config: GMMConfig, stats: Mapping[str, torch.Tensor]):
        # Per component: a mean and a scale per action dim, and a logit.
        super().__init__(config, stats, outputs_per_step=config.gmm_components * (2 * config.action_dim + 1))

    def head_output(self, raw: torch.Tensor):
        return gmm_parameters(raw, self.config.gmm_components, self.config.action_dim)


class GMMPolicy(BCPolicy):
    """A `BCPolicy` whose network writes the mixture (`GMM_KEYS`) and whose ``mode`` writes from it
    ``"action"`` (``"action_chunk"``): the mean of the most likely component. Trained by
    `GMMActionLoss` (its `loss`), scored by `validation_errors` on the action it takes."""

    config_class = GMMConfig

    def __init__(self, config: GMMConfig, stats: Mapping[str, torch.Tensor]):
        action_key = ACTION_CHUNK if config.action_chunk > 1 else ACTION
        super().__init__(
            config,
            stats,
            network=GMMNetwork(config, stats),
            out_keys=GMM_KEYS,
            mode=TensorDictModule(most_likely_mean, in_keys=[GMM_LOC, GMM_LOGITS], out_keys=[action_key]),
        )

    def mixture(self) -> TensorDictModule:
        """The network alone, sharing this policy's weights: writes the mixture (`GMM_KEYS`) of each
        row of a batch, what `GMMActionLoss` scores."""
        return self._network()

    def loss(self) -> GMMActionLoss:
        return GMMActionLoss(self.mixture(), chunked=self.config.action_chunk > 1)
