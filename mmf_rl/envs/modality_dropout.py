"""`ModalityDropout`: simulated sensor outages for a multimodal TorchRL env.

Reads the `mmf_rl.keys` contract per env step (``("obs", m)`` single frames and ``("present", m)``
flags, as `MultimodalPushTorchEnv` emits them) and keeps per-env state shaped by the env's batch
size, so it works on a single env and on `SerialEnv`/`ParallelEnv` alike. Seeded outages per
modality: an absent modality's data is zeroed and its
``("present", m)`` flag cleared; specs are unchanged. It needs no model, so it sits with the
simulator; the forecasting transforms built on the same per-env conventions are in `mmf_rl.rl`.

The three ways a sensor fails (``outage=``): ``"bursts"`` (dropped readings: outages of a few
steps that recover), ``"episode"`` (unplugged: out for a whole episode) and ``"dies"`` (breaks
during the episode: works for a drawn number of steps, then is out until the episode ends).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite
from torchrl.envs.transforms import Compose, Transform

from mmf_rl import keys

RESET_KEY = "_reset"
Outage = Literal["bursts", "episode", "dies"]
OUTAGES: tuple[str, ...] = ("bursts", "episode", "dies")
NEVER = torch.iinfo(torch.long).max  # the onset of an outage that does not happen this episode


def reset_rows(
    tensordict: TensorDictBase, batch_size: torch.Size, known_batch_size: torch.Size | None, owner: str
) -> torch.Tensor:
    """The envs a reset applies to, flattened to ``[n]``: ``"_reset"`` if given, else all.

    A transform allocates its per-env state on the first reset of a batch shape, so a batch it
    has not seen must be reset whole.
    """
    n = batch_size.numel()
    reset = tensordict.get(RESET_KEY, None) if tensordict is not None else None
    # "_reset" carries the done spec's trailing dim ([*batch, 1]).
    rows = torch.ones(n, dtype=torch.bool) if reset is None else reset.reshape(n, -1).any(-1).cpu()
    if known_batch_size != batch_size and not rows.all():
        raise RuntimeError(
            f"{owner}: partial reset of an env batch {list(batch_size)} it has not seen; "
            "reset every env first"
        )
    return rows


def not_standalone(name: str) -> RuntimeError:
    return RuntimeError(
        f"{name} keeps per-env state across steps and only runs inside a TransformedEnv "
        "(env.reset / env.step); it cannot be applied to a stored tensordict"
    )


# -- ModalityDropout ---------------------------------------------------------------------------


@dataclass(frozen=True)
class UniformBursts:
    """Outage lengths uniform over ``[min_steps, max_steps]`` steps (inclusive).

    Args:
        min_steps (int): the shortest outage, ``>= 1``.
        max_steps (int): the longest outage, ``>= min_steps``.

    Raises:
        ValueError: unless ``1 <= min_steps <= max_steps``.
    """

    min_steps: int
    max_steps: int

    def __post_init__(self):
        if not 1 <= self.min_steps <= self.max_steps:
            raise ValueError(
                f"UniformBursts needs 1 <= min_steps <= max_steps, found "
                f"min_steps={self.min_steps}, max_steps={self.max_steps}"
            )

    def sample(self, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
        """Draw outage lengths.

        Args:
            shape (torch.Size): the shape of the draws.
            generator (torch.Generator): the generator drawn from.

        Returns:
            ``long`` lengths of ``shape``.
        """
        return torch.randint(self.min_steps, self.max_steps + 1, shape, generator=generator)


@dataclass(frozen=True)
class GeometricBursts:
    """Outage lengths geometric on ``{1, 2, ...}`` with mean ``mean_steps`` (memoryless recovery).

    Args:
        mean_steps (float): the mean outage length, ``>= 1`` (``1``: every outage lasts one step).

    Raises:
        ValueError: ``mean_steps < 1``.
    """

    mean_steps: float

    def __post_init__(self):
        if not self.mean_steps >= 1:
            raise ValueError(f"GeometricBursts needs mean_steps >= 1, found {self.mean_steps}")

    def sample(self, shape: torch.Size, generator: torch.Generator) -> torch.Tensor:
        """Draw outage lengths.

        Args:
            shape (torch.Size): the shape of the draws.
            generator (torch.Generator): the generator drawn from.

        Returns:
            ``long`` lengths of ``shape``.
        """
        if self.mean_steps == 1:
            return torch.ones(shape, dtype=torch.long)
        # Inverse CDF: P(L > k) = (1 - p)^k with p = 1 / mean.
        u = 1.0 - torch.rand(shape, generator=generator, dtype=torch.float64)  # (0, 1]
        return (torch.log(u) / math.log(1.0 - 1.0 / self.mean_steps)).floor().long() + 1


def outage_start_prob(fraction: float, mean_burst: float) -> float:
    """The per-step outage start probability (``ModalityDropout(outage="bursts")``'s ``outage_prob``) that
    leaves a modality absent ``fraction`` of the steps when its outages last ``mean_burst`` steps on
    average.

    Up runs last ``1 / p`` steps on average (an outage starts with probability ``p`` at each step
    the modality is up), outages ``mean_burst``, so the absent fraction is
    ``mean_burst / (mean_burst + 1 / p)``. A fraction above ``mean_burst / (mean_burst + 1)`` would
    need ``p > 1``: it is capped there (an outage after every single reading).

    Args:
        fraction (float): the share of steps the modality should be absent, in ``[0, 1)``.
        mean_burst (float): the mean outage length in steps, ``>= 1``.

    Returns:
        ``p``, in ``[0, 1]``.

    Raises:
        ValueError: ``fraction`` outside ``[0, 1)`` or ``mean_burst < 1``.

    Examples:
        >>> from mmf_rl.envs import outage_start_prob
        >>> outage_start_prob(0.2, mean_burst=5.0)  # absent 20% of the steps, 5 at a time
        0.05
    """
    if not 0.0 <= fraction < 1.0 or mean_burst < 1:
        raise ValueError(
            f"outage_start_prob needs 0 <= fraction < 1 and mean_burst >= 1, found fraction={fraction}, "
            f"mean_burst={mean_burst}"
        )
    return min(1.0, fraction / (mean_burst * (1.0 - fraction)))


def replay_outages(outages: Mapping[str, Mapping[str, float]], seed: int = 0) -> Compose:
    """One ``ModalityDropout`` per modality that replays measured outages: ``{modality: {"fraction":
    f, "mean_burst": L}}`` (what ``mmf-rl inspect`` reports and ``WindowDataset.observed_outages``
    holds) becomes outages that start with ``outage_start_prob(f, L)`` and last ``GeometricBursts(L)``.
    Modalities never or always absent (``f`` of 0 or 1) get no transform.

    Args:
        outages (Mapping[str, Mapping[str, float]]): ``{modality: {"fraction": f, "mean_burst": L}}``.
        seed (int, optional): the first transform's seed; the ``i``-th modality (sorted by name) gets
            ``seed + i``. Defaults to ``0``.

    Returns:
        A `Compose` of one `ModalityDropout` (``outage="bursts"``) per modality with outages.

    Raises:
        ValueError: no modality has a fraction strictly between 0 and 1.
    """
    transforms = [
        ModalityDropout(
            [name],
            outage_prob=outage_start_prob(o["fraction"], o["mean_burst"]),
            bursts=GeometricBursts(o["mean_burst"]),
            outage="bursts",
            seed=seed + i,
        )
        for i, (name, o) in enumerate(sorted(outages.items()))
        if 0.0 < o["fraction"] < 1.0
    ]
    if not transforms:
        raise ValueError(
            f"replay_outages: no modality in {sorted(outages)} has outages to replay (every fraction is "
            "0 or 1)"
        )
    return Compose(*transforms)


class ModalityDropout(Transform):
    """Seeded sensor outages: zero ``("obs", m)`` and clear ``("present", m)`` while ``m`` is out.

    Args:
        modalities (Sequence[str]): names of the modalities that can fail.
        outage_prob (float | Mapping[str, float], optional): one probability for all, or one per
            modality (a mapping over ``modalities``). ``outage="bursts"``: probability that an
            outage starts at a step where the modality is up; ``"episode"``: probability that the
            modality is out for the whole episode; ``"dies"``: probability that it dies during the
            episode. Defaults to ``0.05``.
        bursts (UniformBursts | GeometricBursts, optional): for ``"bursts"``, the outage length
            distribution; an outage lasts exactly the drawn number of steps unless the episode ends
            first. Defaults to ``UniformBursts(1, 10)``.
        outage (str, optional): ``"bursts"`` (default), ``"episode"`` or ``"dies"`` (see the module
            docstring).
        dies_after (UniformBursts | GeometricBursts, optional): for ``"dies"``, the number of
            readings the modality delivers before it dies (at least 1): with ``k`` drawn,
            observations ``0 .. k-1`` of the episode (0 is the reset observation) are present and
            every later one is absent. The default, uniform over 1..49, spreads the death over the
            push env's 50-step episodes; a ``k`` past the episode's end means it survives that
            episode. `GeometricBursts(mean)` gives a constant failure rate per step.
        seed (int, optional): seed of the transform's own ``torch.Generator``; the same seed, outage
            type, env batch size and sequence of resets and steps give the same outages. Defaults to
            ``0``.

    Every env (every row of a batched env) draws independently. The reset observation counts as
    a step. With ``"bursts"``, after an outage the modality delivers at least one reading before
    it can fail again, so each outage is one run of absent steps of the drawn length. A reset
    clears the outages of the envs that reset (honouring ``"_reset"`` masks) and draws afresh for
    them: an ``"episode"`` or ``"dies"`` outage is drawn once per episode, at its reset. The
    transform keeps per-env state, so it only runs inside a `TransformedEnv`.

    Raises:
        ValueError: no modality, an unknown ``outage``, an ``outage_prob`` mapping that does not
            name exactly ``modalities``, or a probability outside ``[0, 1]``.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from mmf_rl.envs import ModalityDropout, MultimodalPushTorchEnv, UniformBursts
        >>> env = TransformedEnv(
        ...     MultimodalPushTorchEnv(image_size=16),
        ...     ModalityDropout(["image", "force"], outage_prob=0.3, bursts=UniformBursts(2, 3), seed=0),
        ... )
        >>> rollout = env.rollout(4)
        >>> rollout["next", "present", "force"]  # out for two steps, then back
        tensor([ True,  True, False, False])
        >>> rollout["next", "obs", "force"][2:].abs().sum()  # an absent reading is zeroed
        tensor(0.)
        >>> rollout["next", "present", "proprio"].all()  # not listed: never out
        tensor(True)
        >>> env.close()
    """

    def __init__(
        self,
        modalities: Sequence[str],
        outage_prob: float | Mapping[str, float] = 0.05,
        bursts: UniformBursts | GeometricBursts = UniformBursts(1, 10),
        outage: Outage = "bursts",
        dies_after: UniformBursts | GeometricBursts = UniformBursts(1, 49),
        seed: int = 0,
    ):
        modalities = list(modalities)
        if not modalities:
            raise ValueError("ModalityDropout needs at least one modality name")
        if outage not in OUTAGES:
            raise ValueError(f"ModalityDropout(outage={outage!r}): expected one of {list(OUTAGES)}")
        if isinstance(outage_prob, Mapping):
            unknown = sorted(set(outage_prob) - set(modalities))
            missing = sorted(set(modalities) - set(outage_prob))
            if unknown or missing:
                raise ValueError(
                    f"ModalityDropout: outage_prob names {sorted(outage_prob)} but modalities are "
                    f"{modalities}; give one probability per modality"
                )
            probs = [float(outage_prob[m]) for m in modalities]
        else:
            probs = [float(outage_prob)] * len(modalities)
        if any(not 0.0 <= p <= 1.0 for p in probs):
            raise ValueError(f"ModalityDropout: outage probabilities must be in [0, 1], found {probs}")
        obs_keys = [keys.obs_key(m) for m in modalities]
        present_keys = [keys.present_key(m) for m in modalities]
        super().__init__(in_keys=obs_keys + present_keys, out_keys=obs_keys + present_keys)
        self.modalities = modalities
        self.outage_prob = torch.tensor(probs)
        self.bursts = bursts
        self.outage = outage
        self.dies_after = dies_after
        self.seed = seed
        self.generator = torch.Generator().manual_seed(seed)
        # Per env (flattened batch) and modality: steps of the current outage still to come (for
        # "episode" and "dies": readings still to come before it starts, then "forever"), and
        # whether the last observation was absent.
        self._remaining: torch.Tensor | None = None
        self._absent: torch.Tensor | None = None
        self._batch_size: torch.Size | None = None

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Check the env has the modalities; the spec is unchanged (outages change values only).

        Args:
            observation_spec (Composite): the env's observation spec.

        Returns:
            ``observation_spec`` itself.

        Raises:
            KeyError: the env lacks ``("obs", m)`` or ``("present", m)`` of a listed modality.
        """
        available = sorted(
            k[1] for k in observation_spec.keys(True, True) if isinstance(k, tuple) and k[0] == keys.OBS
        )
        missing = [k for k in self.in_keys if k not in observation_spec.keys(True, True)]
        if missing:
            raise KeyError(f"ModalityDropout: the env has no {missing}; its modalities are {available}")
        return observation_spec

    def _draw(self, rows: torch.Tensor) -> None:
        """Advance the "bursts" outage state of ``rows`` by one observation."""
        shape = self._remaining.shape
        # Draws for every row and modality each time, so the stream does not depend on outcomes.
        starts = torch.rand(shape, generator=self.generator) < self.outage_prob
        lengths = self.bursts.sample(shape, self.generator)
        starts &= ~self._absent & rows[:, None]
        remaining = torch.where(starts, lengths, self._remaining)
        absent = remaining > 0
        self._absent = torch.where(rows[:, None], absent, self._absent)
        self._remaining = torch.where(rows[:, None], (remaining - 1).clamp_min(0), self._remaining)

    def _apply_outages(self, tensordict: TensorDictBase) -> TensorDictBase:
        absent = self._absent.reshape(*self._batch_size, len(self.modalities))
        for i, name in enumerate(self.modalities):
            out = absent[..., i]
            obs = tensordict.get(keys.obs_key(name))
            mask = out.reshape(*out.shape, *[1] * (obs.dim() - out.dim()))
            tensordict.set(keys.obs_key(name), obs.masked_fill(mask, 0))
            tensordict.set(keys.present_key(name), tensordict.get(keys.present_key(name)) & ~out)
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        rows = reset_rows(tensordict, batch_size, self._batch_size, "ModalityDropout")
        if self._batch_size != batch_size:
            self._batch_size = batch_size
            self._remaining = torch.zeros(batch_size.numel(), len(self.modalities), dtype=torch.long)
            self._absent = torch.zeros(batch_size.numel(), len(self.modalities), dtype=torch.bool)
        self._remaining[rows] = 0
        self._absent[rows] = False
        if self.outage == "bursts":
            self._draw(rows)
        else:
            self._draw_episode(rows)
            self._advance_episode(rows)
        return self._apply_outages(tensordict_reset)

    def _draw_episode(self, rows: torch.Tensor) -> None:
        """Draw the "episode" or "dies" outage of the episodes ``rows`` start: the readings before it."""
        shape = self._remaining.shape
        fails = torch.rand(shape, generator=self.generator) < self.outage_prob
        onset = (
            self.dies_after.sample(shape, self.generator)
            if self.outage == "dies"
            else torch.zeros(shape, dtype=torch.long)
        )
        onset = torch.where(fails, onset, NEVER)
        self._remaining = torch.where(rows[:, None], onset, self._remaining)

    def _advance_episode(self, rows: torch.Tensor) -> None:
        """One observation of an "episode" or "dies" outage: absent once its onset is reached."""
        self._absent = torch.where(rows[:, None], self._remaining <= 0, self._absent)
        self._remaining = torch.where(
            rows[:, None] & (self._remaining > 0) & (self._remaining < NEVER),
            self._remaining - 1,
            self._remaining,
        )

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        if self._batch_size is None:
            raise RuntimeError(
                "ModalityDropout: the env was stepped before its first reset; call env.reset()"
            )
        every_env = torch.ones(self._batch_size.numel(), dtype=torch.bool)
        if self.outage == "bursts":
            self._draw(every_env)
        else:
            self._advance_episode(every_env)
        return self._apply_outages(next_tensordict)

    def observe_reset(self, observation: TensorDictBase) -> TensorDictBase:
        """Draw every env's outages for a reset's ``observation`` (env batch ``[*batch]``) and apply
        them, as ``env.reset()`` does in a `TransformedEnv`: for a caller that replays recorded
        episodes through the outages (``benchmarks/push/replayed_outages.py``).

        Args:
            observation (TensorDictBase): the reset observation, changed in place.

        Returns:
            ``observation`` with the outages applied.
        """
        return self._reset(observation.empty(), observation)

    def observe_step(self, observation: TensorDictBase) -> TensorDictBase:
        """Advance every env's outages by a step's ``observation`` and apply them, as ``env.step()``
        does in a `TransformedEnv` (see :meth:`observe_reset`).

        Args:
            observation (TensorDictBase): the step's observation, changed in place.

        Returns:
            ``observation`` with the outages applied.
        """
        return self._call(observation)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Refused: the outages are per-env state that only a `TransformedEnv`'s reset and step advance.

        Args:
            tensordict (TensorDictBase): unused.

        Raises:
            RuntimeError: always.
        """
        raise not_standalone("ModalityDropout")
