"""Paired bootstrap over groups of test windows: cells with intervals, "best or tied", the table.

Hand-written: a paired bootstrap over groups (episodes) of ratio means, shared by many cells, is a
few tensor lines; ``scipy.stats.bootstrap`` resamples each statistic independently (no pairing).
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from dataclasses import dataclass, field

import torch

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
LEVEL = 0.95
# Fewer test episodes than this: an episode bootstrap says little, resample blocks of windows instead.
MIN_EPISODES = 10

ErrorRows = dict[str, list]  # {"window": [...], "episode": [...], "squared_error": [...]} of one run
EntryErrors = dict[str, dict[str, list[ErrorRows]]]  # label -> subset -> the rows of each seed


@dataclass
class Cell:
    """One entry x subset: MSE averaged over seeds, its bootstrap interval and resampled values.

    Args:
        mean (float): the MSE, mean over seeds.
        low (float): the interval's lower end.
        high (float): its upper end.
        per_seed (list[float]): each seed's MSE.
        windows (int): the test windows scored.
        samples (torch.Tensor): ``[resamples]``, the statistic on each resample (shared resamples make
            two cells' difference a paired comparison).
    """

    mean: float
    low: float
    high: float
    per_seed: list[float]
    windows: int
    samples: torch.Tensor = field(repr=False)

    def to_dict(self) -> dict:
        """The cell without its resamples, for a JSON report."""
        return {
            "mean": self.mean,
            "low": self.low,
            "high": self.high,
            "per_seed": self.per_seed,
            "windows": self.windows,
        }


def episode_totals(
    episodes: Sequence, errors: Sequence[float], order: Sequence
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-group sum of ``errors`` and window count, groups (episodes) in ``order``.

    Args:
        episodes (Sequence): each window's group.
        errors (Sequence[float]): each window's squared error.
        order (Sequence): the groups, in the order of the bootstrap's weights.

    Returns:
        ``(sums, counts)``, each float64 ``[E]``.

    Raises:
        ValueError: a window's group is not in ``order``.
    """
    index = {episode: i for i, episode in enumerate(order)}
    unknown = sorted(set(episodes) - set(index))
    if unknown:
        raise ValueError(
            f"windows of episodes {unknown[:5]} are not among the test episodes {list(order)[:10]}..."
        )
    positions = torch.tensor([index[e] for e in episodes], dtype=torch.long)
    sums = torch.zeros(len(order), dtype=torch.float64).index_add_(
        0, positions, torch.as_tensor(errors, dtype=torch.float64)
    )
    counts = torch.bincount(positions, minlength=len(order)).to(torch.float64)
    return sums, counts


def bootstrap_weights(
    num_episodes: int, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED
) -> torch.Tensor:
    """``[resamples, E]``: how many times each episode is drawn in each resample (with replacement).

    Drawn once from one seeded generator and applied to every cell, so all entries, seeds and
    subsets are compared on the same resampled test sets (a paired bootstrap).

    Args:
        num_episodes (int): ``E``, the groups resampled.
        resamples (int, optional): the resamples. Defaults to ``2000``.
        seed (int, optional): the generator's seed. Defaults to ``0``.

    Returns:
        float64 ``[resamples, E]``; each row sums to ``E``.
    """
    generator = torch.Generator().manual_seed(seed)
    draws = torch.randint(num_episodes, (resamples, num_episodes), generator=generator)
    return torch.zeros(resamples, num_episodes, dtype=torch.float64).scatter_add_(
        1, draws, torch.ones_like(draws, dtype=torch.float64)
    )


def bootstrap_cell(
    totals: Sequence[tuple[torch.Tensor, torch.Tensor]], weights: torch.Tensor, level: float = LEVEL
) -> Cell:
    """The seed-mean MSE of one cell from each seed's ``episode_totals``, with its percentile interval.

    On each resample every seed's MSE is the window-weighted mean over the drawn episodes; the
    statistic is their mean over seeds (the interval is over test episodes, not over seeds).

    Args:
        totals (Sequence[tuple[torch.Tensor, torch.Tensor]]): each seed's :func:`episode_totals`.
        weights (torch.Tensor): :func:`bootstrap_weights`, shared by every cell.
        level (float, optional): the interval's coverage. Defaults to ``0.95``.

    Returns:
        The cell.

    Raises:
        ValueError: the seeds were scored on different windows.

    Examples:
        >>> from mmf_rl.compare import bootstrap_cell, bootstrap_weights, episode_totals
        >>> episodes = [0, 0, 1, 1, 2, 2, 3, 3]  # two test windows in each of four episodes
        >>> seeds = [[0.1, 0.3, 0.2, 0.2, 0.5, 0.1, 0.2, 0.4], [0.2, 0.2, 0.3, 0.1, 0.4, 0.2, 0.3, 0.3]]
        >>> totals = [episode_totals(episodes, errors, order=[0, 1, 2, 3]) for errors in seeds]
        >>> cell = bootstrap_cell(totals, bootstrap_weights(4))
        >>> round(cell.mean, 3), cell.windows, cell.low <= cell.mean <= cell.high
        (0.25, 8, True)
    """
    sums = torch.stack([s for s, _ in totals])  # [S, E]
    counts = totals[0][1]
    if any(not torch.equal(c, counts) for _, c in totals):
        raise ValueError(
            "the seeds of one cell were scored on different test windows; compare like with like"
        )
    per_seed = sums.sum(1) / counts.sum()
    samples = ((weights @ sums.T) / (weights @ counts)[:, None]).mean(1)  # a resample without windows: nan
    low, high = torch.nanquantile(
        samples, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=samples.dtype)
    )
    return Cell(
        float(per_seed.mean()), float(low), float(high), per_seed.tolist(), int(counts.sum()), samples
    )


def overlap(a: Cell, b: Cell) -> bool:
    return a.low <= b.high and b.low <= a.high


def best_or_tied(cells: dict[str, Cell], label: str) -> bool:
    """``cells[label]`` has the lowest mean of ``cells`` or an interval overlapping the best one's."""
    best = min(cells.values(), key=lambda c: c.mean)
    return cells[label].mean <= best.mean or overlap(cells[label], best)


def difference_interval(a: Cell, b: Cell, level: float = LEVEL) -> tuple[float, float]:
    """Interval of ``a - b`` over the shared resamples (the paired comparison)."""
    diff = a.samples - b.samples
    low, high = torch.nanquantile(diff, torch.tensor([(1 - level) / 2, (1 + level) / 2], dtype=diff.dtype))
    return float(low), float(high)


def ordered_subsets(names: Sequence[str], lead: Sequence[str] = ()) -> list[str]:
    """The ``lead`` subsets first (the headline ones), then the others in their given order."""
    return [s for s in lead if s in names] + [s for s in names if s not in lead]


@dataclass
class Table:
    """The comparison's cells, entry by subset.

    Args:
        subsets (list[str]): the presence subsets, in headline order.
        cells (dict[str, dict[str, Cell]], optional): ``{label: {subset: cell}}``.
        kinds (dict[str, str], optional): each entry's kind (``paper``, ``zero-fill``, ...).
        bases (dict[str, str], optional): ``{label: the entry it is compared with}``, for the kinds
            that have one.
    """

    subsets: list[str]
    cells: dict[str, dict[str, Cell]] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)
    bases: dict[str, str] = field(default_factory=dict)

    def labels(self, *kinds: str) -> list[str]:
        """The entries of these kinds, in table order.

        Args:
            *kinds (str): entry kinds.

        Returns:
            Their labels.
        """
        return [label for label, kind in self.kinds.items() if kind in kinds]

    def degradation(self, label: str, subset: str) -> float:
        """Relative MSE increase against the same entry with all modalities."""
        return self.cells[label][subset].mean / self.cells[label]["all"].mean - 1

    def mean_degradation(self, label: str) -> float:
        """The entry's :meth:`degradation` averaged over its subsets other than ``"all"``.

        Args:
            label (str): the entry.

        Returns:
            The mean relative MSE increase.
        """
        return statistics.fmean(
            self.degradation(label, s) for s in self.subsets if s != "all" and s in self.cells[label]
        )

    def wins(self, rival_kinds: tuple[str, ...], subsets: Sequence[str]) -> tuple[int, int]:
        """(subsets where ``paper`` is best or tied among itself and the rivals, subsets compared)."""
        rivals = self.labels(*rival_kinds)
        won = compared = 0
        for s in subsets:
            cells = {label: self.cells[label][s] for label in ["paper", *rivals] if s in self.cells[label]}
            if "paper" not in cells or len(cells) < 2:
                continue
            compared += 1
            won += best_or_tied(cells, "paper")
        return won, compared

    def fusion_spread(self) -> float | None:
        """(max - min) / min of the all-modality MSE over the paper model and its fusion ablations."""
        means = [self.cells[label]["all"].mean for label in ["paper", *self.labels("fusion")]]
        return max(means) / min(means) - 1 if len(means) > 1 else None


def build_table(
    errors: EntryErrors,
    kinds: dict[str, str],
    subset_names: Sequence[str],
    unit: str = "episode",
    lead: Sequence[str] = (),
    bases: dict[str, str] | None = None,
) -> tuple[Table, list]:
    """Cells with paired bootstrap intervals from every entry's per-window errors.

    Args:
        errors (EntryErrors): ``{label: {subset: [each seed's rows]}}``, rows ``{"window", "episode",
            "squared_error"}`` (``"block"`` too with ``unit="block"``).
        kinds (dict[str, str]): each entry's kind.
        subset_names (Sequence[str]): the subsets, in their order.
        unit (str, optional): the row key naming the groups the bootstrap resamples (``"episode"``,
            the default, or ``"block"``, :func:`bootstrap_unit`).
        lead (Sequence[str], optional): the headline subsets, put first.
        bases (dict[str, str], optional): each entry's base, for the kinds that have one.

    Returns:
        ``(table, groups)``: the table (subsets ``lead`` first) and the groups, sorted.
    """
    groups = sorted({e for rows in all_rows(errors) for e in rows[unit]})
    weights = bootstrap_weights(len(groups))
    table = Table(subsets=ordered_subsets(subset_names, lead), kinds=dict(kinds), bases=dict(bases or {}))
    for label, per_subset in errors.items():
        table.cells[label] = {
            name: bootstrap_cell(
                [episode_totals(r[unit], r["squared_error"], groups) for r in seeds], weights
            )
            for name, seeds in per_subset.items()
        }
    return table, groups


def all_rows(errors: EntryErrors) -> list[ErrorRows]:
    return [rows for per_subset in errors.values() for seeds in per_subset.values() for rows in seeds]


def add_blocks(errors: EntryErrors, block: int) -> None:
    """Give every scored window a ``"block"``: ``(episode, (window - the episode's first test window)
    // block)``, the same block for a window in every entry, seed and subset."""
    first: dict[int, int] = {}
    for rows in all_rows(errors):
        for window, episode in zip(rows["window"], rows["episode"], strict=True):
            first[episode] = min(first.get(episode, window), window)
    for rows in all_rows(errors):
        rows["block"] = [
            (episode, (window - first[episode]) // block)
            for window, episode in zip(rows["window"], rows["episode"], strict=True)
        ]


def bootstrap_unit(errors: EntryErrors, block: int, min_episodes: int = MIN_EPISODES) -> str:
    """The group the bootstrap resamples: test episodes when there are enough, else blocks of windows.

    Blocks are non-overlapping runs of ``block`` consecutive windows of an episode (with ``block`` =
    H + T at stride 1, windows of non-adjacent blocks share no frame).

    Args:
        errors (EntryErrors): every entry's rows; given ``"block"`` entries in place when blocks are
            chosen.
        block (int): windows per block.
        min_episodes (int, optional): the fewest test episodes an episode bootstrap needs. Defaults to
            ``10``.

    Returns:
        ``"episode"`` or ``"block"``.
    """
    episodes = {e for rows in all_rows(errors) for e in rows["episode"]}
    if len(episodes) >= min_episodes:
        return "episode"
    add_blocks(errors, block)
    return "block"
