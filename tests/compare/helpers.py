"""Fixed inputs shared by the mmf_rl.compare tests."""

from __future__ import annotations

import torch

from mmf_rl.compare.bootstrap import Cell

PUSH_MODALITIES = ["force", "image", "proprio"]
PUSH_SUBSETS = [
    "all",
    "without_force",
    "without_image",
    "without_proprio",
    "only_force",
    "only_image",
    "only_proprio",
]
PAPER_SUBSETS = ("all", "without_proprio", "without_force")


def cell(mean: float, low: float | None = None, high: float | None = None) -> Cell:
    low = mean - 0.01 if low is None else low
    high = mean + 0.01 if high is None else high
    return Cell(mean, low, high, [mean], 10, torch.full((4,), mean))


def rows(windows: list[int], episodes: list[int], errors: list[float] | None = None) -> dict:
    return {"window": windows, "episode": episodes, "squared_error": errors or [1.0] * len(windows)}


# A fixed comparison of eight entries of every kind on the push subsets: two seeds, 6 test episodes of
# 4 windows; each entry's level grows by subset and wobbles by window, episode and seed. The retrained
# baseline is scored on the paper's subsets only.
FIXED_KINDS = {
    "paper": "paper",
    "paper prior=learned": "variant",
    "LF-LSTM": "zero-fill",
    "MulT": "zero-fill",
    "LF-LSTM (retrained)": "retrained",
    "paper fusion=sum": "fusion",
    "paper prior=learned, fusion=sum": "learned fusion",
    "paper w/o L_mis": "ablation",
}
FIXED_LEVELS = [0.30, 0.28, 0.33, 0.45, 0.25, 0.36, 0.31, 0.32]
FIXED_BASES = {"paper prior=learned, fusion=sum": "paper prior=learned", "LF-LSTM (retrained)": "LF-LSTM"}


def fixed_errors() -> dict:
    out = {}
    for li, (label, level) in enumerate(zip(FIXED_KINDS, FIXED_LEVELS, strict=True)):
        per_subset = {}
        for si, s in enumerate(PUSH_SUBSETS):
            if label == "LF-LSTM (retrained)" and s not in PAPER_SUBSETS:
                continue
            episodes = [e for e in range(6) for _ in range(4)]
            per_subset[s] = [
                rows(
                    list(range(24)),
                    episodes,
                    [
                        level * (1 + 0.15 * si) * (1 + 0.05 * ((7 * w + 3 * e + li + seed) % 5))
                        for w, e in enumerate(episodes)
                    ],
                )
                for seed in (0, 1)
            ]
        out[label] = per_subset
    return out
