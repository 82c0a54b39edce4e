"""Missingness protocols of the paper: missing training data, and fixed evaluation subsets.

Training: a fraction ``p`` of the training samples lacks modality ``m`` (the paper's "ratio of
modality missing as the number of samples"), the same samples every epoch, chosen by a seed.
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
    """
    result = {name: mask.clone() for name, mask in present.items()}
    n = len(next(iter(present.values())))
    dropped = {}
    for name, fraction in sorted(missing.items()):
        generator = torch.Generator().manual_seed(seed * 1_000_003 + zlib.crc32(name.encode()))
        chosen = torch.zeros(n, dtype=torch.bool)
        chosen[torch.randperm(n, generator=generator)[: round(fraction * n)]] = True
        dropped[name] = chosen
        result[name] &= ~chosen
    nothing_left = ~torch.stack(list(result.values())).any(0)
    for name, chosen in dropped.items():
        result[name] |= present[name] & chosen & nothing_left
    return result


def presence_subsets(modalities: list[str]) -> Iterator[tuple[str, dict[str, bool]]]:
    """Named evaluation subsets: ``all``, ``without_<m>`` for each ``m``, ``only_<m>`` for each ``m``.

    A subset equal to an earlier one (e.g. ``only_a`` when there are two modalities and
    ``without_b`` was given) is skipped, so each presence pattern is evaluated once.
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

    Returns a new TensorDict (possibly with fewer samples: an ``only_image`` subset drops the
    samples whose camera was missing anyway).
    """
    out = batch.exclude(PRESENT)  # a new TensorDict: the caller's presence stays untouched
    keep = torch.zeros(batch.batch_size[0], dtype=torch.bool)
    for name, kept in subset.items():
        present = batch.get(present_key(name)) & kept
        out.set(present_key(name), present)
        keep |= present
    return out[keep]
