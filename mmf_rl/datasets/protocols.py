"""Missingness protocols of the paper: missing training data, and fixed evaluation subsets.

Training: a fraction ``p`` of the training samples lacks modality ``m`` (the paper's "ratio of
modality missing as the number of samples"), the same samples every epoch, chosen by a seed.
Or outages replayed: a sensor's measured outage statistics (:func:`outage_statistics`: fraction
of frames absent, mean burst length) drive simulated outage bursts along the frames
(:func:`replayed_outage_frames`, the chain of ``ModalityDropout``), and a window whose observed
frames meet one lacks the modality, as a real outage would make it.
Evaluation: every model is scored on the same named presence subsets: all modalities, each
leave-one-out, each single modality.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator

import torch
from tensordict import TensorDictBase

from mmf_rl.keys import PRESENT, present_key


def training_dropout(
    present: dict[str, torch.Tensor], missing: dict[str, float], seed: int
) -> dict[str, torch.Tensor]:
    """Presence after removing modality ``m`` from ``round(p * n)`` samples, for each ``m: p``.

    Each modality's samples come from its own generator (seeded by ``seed`` and its name), so
    adding a modality to the protocol does not move the others' samples. A removal that would
    leave a sample with no modality at all is not applied: such a sample cannot be forecast.

    Args:
        present (dict[str, torch.Tensor]): ``bool [n]`` presence per modality.
        missing (dict[str, float]): ``{modality: p}``, the fraction of samples to remove it from.
        seed (int): the removals' seed.

    Returns:
        The new presence per modality (``present`` is not changed).
    """
    n = len(next(iter(present.values())))
    dropped = {}
    for name, fraction in sorted(missing.items()):
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[torch.randperm(n, generator=_generator(seed, name))[: round(fraction * n)]] = True
        dropped[name] = chosen
    return remove_modalities(present, dropped)


def _generator(seed: int, name: str) -> torch.Generator:
    """A modality's own generator: adding a modality to a protocol does not move another's draws."""
    return torch.Generator().manual_seed(seed * 1_000_003 + zlib.crc32(name.encode()))


def remove_modalities(
    present: dict[str, torch.Tensor], dropped: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """Presence with ``dropped[m]`` samples of each ``m`` removed, except where that would leave a
    sample with no modality at all (it could not be forecast)."""
    result = {
        name: mask & ~dropped[name] if name in dropped else mask.clone() for name, mask in present.items()
    }
    nothing_left = ~torch.stack(list(result.values())).any(0)
    for name, chosen in dropped.items():
        result[name] |= present[name] & chosen & nothing_left
    return result


def outage_statistics(present: torch.Tensor, episode: torch.Tensor) -> dict[str, float]:
    """A sensor's outages from its per-frame presence (frames in order, ``episode`` per frame):
    ``fraction`` of frames absent, ``outages`` (runs of absent frames; a run ends with its
    episode), ``mean_burst`` and ``max_burst`` (run lengths in frames; 0 without outages)."""
    absent = ~present.bool()
    starts = absent.clone()
    starts[1:] &= ~absent[:-1] | (episode[1:] != episode[:-1])
    run = torch.cumsum(starts.long(), 0) - 1
    lengths = torch.bincount(run[absent], minlength=int(starts.sum())) if absent.any() else torch.zeros(0)
    n = len(absent)
    return {
        "fraction": float(absent.sum()) / n if n else 0.0,
        "outages": len(lengths),
        "mean_burst": float(lengths.float().mean()) if len(lengths) else 0.0,
        "max_burst": int(lengths.max()) if len(lengths) else 0,
    }


def replayed_outage_frames(
    n: int, fraction: float, mean_burst: float, generator: torch.Generator
) -> torch.Tensor:
    """``[n]`` bool, True on simulated outage frames: up runs and outages alternate, outages of
    ``GeometricBursts(mean_burst)`` frames starting with ``outage_start_prob(fraction, mean_burst)``
    per frame up, so about ``fraction`` of the frames are out, in bursts like the measured ones."""
    # Imported here for start-up time: the env package loads MuJoCo, which only this replay needs.
    from mmf_rl.envs.modality_dropout import GeometricBursts, outage_start_prob

    up, down = GeometricBursts(1.0 / outage_start_prob(fraction, mean_burst)), GeometricBursts(mean_burst)
    absent = torch.zeros(0, dtype=torch.bool)
    out = bool(torch.rand((), generator=generator) < fraction)  # start in the chain's stationary state
    while len(absent) < n:
        pairs = max(1, int(n / (up.mean_steps + down.mean_steps)) + 1)
        lengths = torch.stack([up.sample((pairs,), generator), down.sample((pairs,), generator)], 1).flatten()
        states = torch.tensor([False, True]).repeat(pairs)
        if out:
            lengths, states, out = lengths[1:], states[1:], False
        absent = torch.cat([absent, states.repeat_interleave(lengths)])
    return absent[:n]


def replay_outages(
    present: dict[str, torch.Tensor],
    observed_rows: dict[str, torch.Tensor],
    outages: dict[str, dict[str, float]],
    n_frames: int,
    seed: int,
) -> dict[str, torch.Tensor]:
    """Window presence after simulated outages: ``outages[m] = {"fraction": f, "mean_burst": L}``
    drives :func:`replayed_outage_frames` over the ``n_frames`` frames, and a window whose
    ``observed_rows[m]`` (``[W, k]`` frame indices it reads for ``m``) meet an outage frame loses
    ``m``. Seeded per modality; a window is never left without any modality."""
    dropped = {}
    for name, o in sorted(outages.items()):
        if 0.0 < o["fraction"] < 1.0:
            frames = replayed_outage_frames(n_frames, o["fraction"], o["mean_burst"], _generator(seed, name))
            dropped[name] = frames[observed_rows[name]].reshape(len(observed_rows[name]), -1).any(1)
    return remove_modalities(present, dropped)


def presence_subsets(modalities: list[str]) -> Iterator[tuple[str, dict[str, bool]]]:
    """Named evaluation subsets: ``all``, ``without_<m>`` for each ``m``, ``only_<m>`` for each ``m``.

    A subset equal to an earlier one (e.g. ``only_a`` when there are two modalities and
    ``without_b`` was given) is skipped, so each presence pattern is evaluated once.

    Args:
        modalities (list[str]): the modality names.

    Yields:
        ``(label, {modality: kept})`` per subset.

    Examples:
        >>> from mmf_rl.datasets import presence_subsets
        >>> [label for label, _ in presence_subsets(["image", "force", "proprio"])]
        ['all', 'without_image', 'without_force', 'without_proprio',
         'only_image', 'only_force', 'only_proprio']
        >>> dict(presence_subsets(["image", "force"]))  # only_image is without_force
        {'all': {'image': True, 'force': True},
         'without_image': {'image': False, 'force': True},
         'without_force': {'image': True, 'force': False}}
    """
    names = list(modalities)
    candidates = [("all", set(names))]
    if len(names) > 1:
        candidates += [(f"without_{m}", set(names) - {m}) for m in names]
    candidates += [(f"only_{m}", {m}) for m in names]
    seen = []
    for label, kept in candidates:
        if kept not in seen:
            seen.append(kept)
            yield label, {m: m in kept for m in names}


def apply_presence_subset(batch: TensorDictBase, subset: dict[str, bool]) -> TensorDictBase:
    """Mark the subset's excluded modalities absent, and keep the samples that still have one.

    Args:
        batch (TensorDictBase): a batch following `mmf_rl.keys`; not changed.
        subset (dict[str, bool]): ``{modality: kept}``, one of :func:`presence_subsets`.

    Returns:
        A new TensorDict, possibly with fewer samples: an ``only_image`` subset drops the samples
        whose camera was missing anyway.
    """
    out = batch.exclude(PRESENT)  # a new TensorDict: the caller's presence stays untouched
    keep = torch.zeros(batch.batch_size[0], dtype=torch.bool)
    for name, kept in subset.items():
        present = batch.get(present_key(name)) & kept
        out.set(present_key(name), present)
        keep |= present
    return out[keep]
