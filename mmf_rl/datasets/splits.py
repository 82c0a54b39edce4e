"""Episode-level splits and normalisation statistics (training split only)."""

from __future__ import annotations

from pathlib import Path

import torch

from mmf_rl.datasets.config import SPLIT_NAMES, DataConfig


def _ranges(ids: list[int]) -> str:
    """``[0, 1, 2, 5]`` -> ``"0..2, 5"``: how a dataset's episode ids are named in an error."""
    parts, ids = [], sorted(ids)
    for i, e in enumerate(ids):
        if i and e == ids[i - 1] + 1:
            continue
        end = e
        while end + 1 in ids:
            end += 1
        parts.append(str(e) if end == e else f"{e}..{end}")
    return ", ".join(parts)


def select_episodes(available: list[int], config: DataConfig, root: Path | str) -> list[int]:
    """The episodes the config selects, checked against the dataset's ``available`` ids.

    ``episodes`` (default: all, or the union of an explicit ``split``) minus ``exclude_episodes``.
    An id the dataset lacks, a split episode left out of the selection, or an empty selection is
    an error naming the key, the ids and what the dataset has.
    """
    lists = {"episodes": config.episodes or [], "exclude_episodes": config.exclude_episodes}
    lists.update({f"split.{name}": ids for name, ids in (config.split or {}).items()})
    for key, ids in lists.items():
        unknown = sorted(set(ids) - set(available))
        if unknown:
            raise ValueError(
                f"data config: `{key}` lists episode(s) {unknown} that the dataset at {root} does not "
                f"have (its episodes: {_ranges(available)})"
            )
    in_split = sorted({e for ids in (config.split or {}).values() for e in ids})
    if config.episodes is not None:
        selected = set(config.episodes)
    else:
        selected = set(in_split) if config.split is not None else set(available)
    selected -= set(config.exclude_episodes)
    for name, ids in (config.split or {}).items():
        left_out = sorted(set(ids) - selected)
        if left_out:
            why = (
                "excluded by `exclude_episodes`"
                if set(left_out) & set(config.exclude_episodes)
                else "not in `episodes`"
            )
            raise ValueError(
                f"data config: `split.{name}` lists episode(s) {left_out}, {why}; select them or "
                f"remove them from `split.{name}`"
            )
    if not selected:
        raise ValueError(
            f"data config: the episode selection (episodes={config.episodes}, exclude_episodes="
            f"{config.exclude_episodes}) leaves no episode of {root} (its episodes: {_ranges(available)})"
        )
    return sorted(selected)


def episode_splits(episodes: list[int], config: DataConfig) -> dict[str, list[int]]:
    """Train/val/test episodes: the config's explicit ``split`` lists, else ``split_fractions``."""
    if config.split is not None:
        return {name: sorted(config.split.get(name, [])) for name in SPLIT_NAMES}
    return split_episodes(episodes, config.split_fractions, config.split_seed)


def split_episodes(
    episodes: list[int], fractions: tuple[float, float, float], seed: int
) -> dict[str, list[int]]:
    """Shuffle episodes with ``seed`` and cut them into train/val/test by ``fractions``.

    Every split with a positive fraction gets at least one episode (so a 4-episode dataset still
    has a val and a test episode); train takes what is left and must keep at least one.

    Args:
        episodes (list[int]): the episode indices.
        fractions (tuple[float, float, float]): train/val/test shares; val and test are rounded, train
            gets the rest.
        seed (int): the shuffle's seed.

    Returns:
        ``{"train": [...], "val": [...], "test": [...]}``, each sorted.

    Raises:
        ValueError: train would be left with no episode.

    Examples:
        >>> from mmf_rl.datasets import split_episodes
        >>> split_episodes(list(range(10)), (0.8, 0.1, 0.1), seed=0)
        {'train': [...], 'val': [...], 'test': [...]}
        >>> {name: len(ids) for name, ids in split_episodes(list(range(4)), (0.8, 0.1, 0.1), 0).items()}
        {'train': 2, 'val': 1, 'test': 1}
    """
    n = len(episodes)
    counts = {name: 0 for name in SPLIT_NAMES}
    for name, fraction in zip(SPLIT_NAMES[1:], fractions[1:], strict=True):
        counts[name] = max(1, round(fraction * n)) if fraction > 0 else 0
    counts["train"] = n - counts["val"] - counts["test"]
    if counts["train"] < 1:
        raise ValueError(
            f"cannot split {n} episode(s) by fractions {list(fractions)} (train/val/test): "
            f"train would get {counts['train']}; record more episodes or lower the val/test fractions"
        )
    order = torch.randperm(n, generator=torch.Generator().manual_seed(seed)).tolist()
    shuffled = [episodes[i] for i in order]
    splits, start = {}, 0
    for name in SPLIT_NAMES:
        splits[name] = sorted(shuffled[start : start + counts[name]])
        start += counts[name]
    return splits


def mean_std(
    values: torch.Tensor, valid: torch.Tensor, std_floor: float, what: str
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-dim mean/std of ``values[valid]`` (float64 accumulation); std floored at ``std_floor``."""
    rows = values[valid].double()
    if rows.shape[0] == 0:
        raise ValueError(
            f"normalisation statistics for {what}: no valid frame in the training split "
            "(all NaN, invalid or absent); check the feature or the split fractions"
        )
    mean = rows.mean(0)
    std = rows.std(0, correction=0) if rows.shape[0] > 1 else torch.zeros_like(mean)
    return mean.float(), std.clamp_min(std_floor).float()


class Normalizer:
    """Normalises vector observations and the target with training-split statistics.

    Args:
        stats (dict[str, torch.Tensor]): a flat ``{"<modality>/mean": tensor, "<modality>/std": ...,
            "target/mean": ..., "target/std": ...}`` dict (stored as float32): store it beside a run
            (``safetensors.torch.save_file(normalizer.stats, ...)``) and rebuild with
            ``Normalizer(stats)``.

    Raises:
        KeyError: ``stats`` lacks ``"target/mean"`` or ``"target/std"``.
    """

    def __init__(self, stats: dict[str, torch.Tensor]):
        self.stats = {k: v.float() for k, v in stats.items()}
        for required in ("target/mean", "target/std"):
            if required not in self.stats:
                raise KeyError(f"normalisation stats lack {required!r}; found {sorted(self.stats)}")

    def normalize(self, name: str, values: torch.Tensor) -> torch.Tensor:
        """``(values - mean) / std`` with the statistics of ``name``.

        Args:
            name (str): a modality, ``"target"`` or ``"future_action"``.
            values (torch.Tensor): ``[..., d]`` in the feature's units.

        Returns:
            The normalised values.
        """
        return (values - self.stats[f"{name}/mean"]) / self.stats[f"{name}/std"]

    def denormalize_target(self, target: torch.Tensor) -> torch.Tensor:
        """Normalised target (or forecast location) back to the target's units.

        Args:
            target (torch.Tensor): ``[..., D]`` in the normalised frame.

        Returns:
            ``target * std + mean``.
        """
        return target * self.stats["target/std"] + self.stats["target/mean"]

    def denormalize_target_scale(self, scale: torch.Tensor) -> torch.Tensor:
        """A forecast standard deviation back to the target's units.

        Args:
            scale (torch.Tensor): ``[..., D]`` in the normalised frame.

        Returns:
            ``scale * std``.
        """
        return scale * self.stats["target/std"]
