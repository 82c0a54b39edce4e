"""The sealed protocol's arithmetic: which models the selection stage trains, which of them an outer
fold may read, and the choice among candidates. Plain names only: no data, no training.

Leave one scene out twice. The outer fold of test scene S trains on the other four scenes; to choose
its options, each of those four, V, is held out in turn as validation while a model trains on the
remaining three. Such a model has two scenes held out, S and V, and is the same model for the outer
fold of V (validated on S): a candidate needs one training per pair of scenes, C(5, 2) = 10 for the
five folds, not 5 x 4 = 20. The choice for S reads only the pairs that hold S out, scored on their
other scene, so no run it reads has trained on S or been scored on it.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from itertools import combinations, product

PAIR_SEPARATOR = "+"


def pair_name(a: str, b: str) -> str:
    """The name of the model trained with scenes ``a`` and ``b`` held out (``eth+hotel``): one name
    whichever outer fold asks for it."""
    return PAIR_SEPARATOR.join(sorted((a, b)))


def is_pair(name: str) -> bool:
    """Whether ``name`` names a held-out pair (an inner run's data) rather than an outer fold."""
    return PAIR_SEPARATOR in name


def pair_scenes(pair: str) -> tuple[str, str]:
    """The two scenes a pair holds out."""
    a, b = pair.split(PAIR_SEPARATOR)
    return a, b


def training_scenes(scenes: Iterable[str], pair: str) -> list[str]:
    """The scenes a pair's model trains on: every other one (three of five)."""
    return sorted(set(scenes) - set(pair_scenes(pair)))


def inner_splits(scenes: Iterable[str], fold: str) -> list[tuple[str, str]]:
    """Outer fold ``fold``'s inner splits, ``(pair, validation scene)``: each of its training scenes
    held out with it, the model of that pair scored on the training scene, never on ``fold``."""
    return [(pair_name(fold, scene), scene) for scene in sorted(scenes) if scene != fold]


def held_out_pairs(scenes: Iterable[str], folds: Iterable[str]) -> list[str]:
    """Every pair whose model an outer fold of ``folds`` reads: the pairs holding one of them out."""
    wanted = set(folds)
    return [pair_name(a, b) for a, b in combinations(sorted(scenes), 2) if wanted & {a, b}]


def grid(options: Mapping[str, Sequence[str]]) -> list[dict[str, str]]:
    """Every combination of the options' values (the joint grid), in the order given: the first
    value of each option first. No options: one candidate, the empty one."""
    names = list(options)
    return [dict(zip(names, values, strict=True)) for values in product(*(options[n] for n in names))]


def candidate_name(candidate: Mapping[str, str]) -> str:
    """A candidate as the page and ``selection.json`` name it: ``augment.rotation=0 sampler=5/5``."""
    return " ".join(f"{name}={value}" for name, value in candidate.items())


def mean_scores(per_scene: Mapping[str, Mapping[str, float]]) -> dict[str, float]:
    """``{candidate: mean over the validation scenes}`` from ``{candidate: {scene: score}}``: every
    scene counts the same, as the literature averages its test scenes."""
    return {name: sum(scores.values()) / len(scores) for name, scores in per_scene.items()}


def choose(means: Mapping[str, float]) -> str:
    """The candidate with the lowest mean; of equal means, the one listed first (``--select``'s order:
    put the value you would keep without evidence first)."""
    return min(means, key=means.__getitem__)
