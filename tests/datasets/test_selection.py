"""Selecting episodes as lerobot users do: `episodes`, `exclude_episodes`, explicit or fractional splits."""

import json
import warnings

import pytest
import torch
from tensordict import TensorDict

from mmf_rl.datasets import DataConfig, WindowDataset
from tests.datasets.conftest import EPISODE_LENGTHS, synthetic_config


def open_quietly(config) -> WindowDataset:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return WindowDataset(config)


def cached_episodes(dataset: WindowDataset) -> list[int]:
    frames = TensorDict.load_memmap(dataset.cache_path / "frames")
    return sorted(set(frames.get("episode").as_subclass(torch.Tensor).tolist()))


def test_episodes_and_exclusions_select_what_is_cached(synthetic_root, tmp_path):
    full = open_quietly(synthetic_config(synthetic_root, tmp_path))
    chosen = open_quietly(synthetic_config(synthetic_root, tmp_path, episodes=[0, 2, 3]))
    assert chosen.cache_path != full.cache_path, "the cache key must include the selection"
    assert cached_episodes(chosen) == [0, 2, 3]
    assert [e[0] for e in chosen.report["episodes"]] == [0, 2, 3]
    assert chosen.report["n_frames"] == sum(EPISODE_LENGTHS[e] for e in (0, 2, 3))
    assert sorted(e for eps in chosen.split_episodes.values() for e in eps) == [0, 2, 3]
    # Rows were remapped, not shifted: each window's target is its own episode's
    # (pose[0] = episode + frame/1000).
    for split in ("train", "val", "test"):
        ids = chosen.split_windows[split]
        target = chosen.normalizer.denormalize_target(chosen.batch(ids).get("target"))
        assert torch.equal(target[:, 0, 0].floor().long(), chosen.window_episode[ids])

    excluded = open_quietly(synthetic_config(synthetic_root, tmp_path, exclude_episodes=[1]))
    assert cached_episodes(excluded) == [0, 2, 3, 4] and excluded.cache_path not in (
        full.cache_path,
        chosen.cache_path,
    )
    assert (
        json.loads((excluded.cache_path / "cache.json").read_text())["n_frames"] == sum(EPISODE_LENGTHS) - 25
    )


def test_an_explicit_split_by_episode_lists(synthetic_root, tmp_path):
    split = {"train": [0, 2], "val": [1], "test": [3]}
    dataset = open_quietly(synthetic_config(synthetic_root, tmp_path, split=split))
    assert dataset.split_episodes == split
    assert cached_episodes(dataset) == [0, 1, 2, 3], "without `episodes`, the split's union is the selection"
    for name, episodes in split.items():
        assert set(dataset.window_episode[dataset.split_windows[name]].tolist()) == set(episodes)
    no_test = open_quietly(synthetic_config(synthetic_root, tmp_path, split={"train": [0, 1], "val": [2]}))
    assert no_test.split_episodes["test"] == [] and len(no_test.split_windows["test"]) == 0


@pytest.mark.parametrize(
    "overrides, message",
    [
        (
            {"episodes": [0, 9]},
            r"`episodes` lists episode\(s\) \[9\] that the dataset .* does not have \(its episodes: 0\.\.4\)",
        ),
        ({"exclude_episodes": [7]}, r"`exclude_episodes` lists episode\(s\) \[7\]"),
        ({"split": {"train": [0, 1], "test": [8]}}, r"`split.test` lists episode\(s\) \[8\]"),
        (
            {"split": {"train": [0, 1], "val": [1, 2]}},
            r"episode\(s\) \[1\] are in both `split.train` and `split.val`",
        ),
        (
            {"split": {"train": [0, 1], "val": [2]}, "exclude_episodes": [2]},
            r"`split.val` lists episode\(s\) \[2\], excluded by `exclude_episodes`",
        ),
        (
            {"split": {"train": [0, 1], "val": [2]}, "episodes": [0, 1]},
            r"`split.val` lists episode\(s\) \[2\], not in `episodes`",
        ),
        ({"split": {"train": [0], "holdout": [1]}}, r"unknown split\(s\) \['holdout'\]"),
        ({"split": {"val": [1]}}, r"`split.train` is empty"),
        ({"episodes": [0, 0]}, r"`episodes` lists episode\(s\) \[0\] more than once"),
        ({"episodes": "0,1"}, r"`episodes` must be a list of episode indices"),
        ({"episodes": [1], "exclude_episodes": [1]}, r"leaves no episode"),
    ],
)
def test_bad_selections_are_named(synthetic_root, tmp_path, overrides, message):
    with pytest.raises(ValueError, match=message):
        WindowDataset(synthetic_config(synthetic_root, tmp_path, **overrides))


def test_g1_recording_split_by_episode_lists(g1_root, tmp_path):
    """The real humanoid recording: only the selected episodes are decoded; the split is the one asked."""
    root = g1_root
    config = DataConfig.from_dict(
        {
            "root": str(root),
            "cache_dir": str(tmp_path),
            "history": 4,
            "horizon": 4,
            "stride": 3,
            "image_size": [32, 32],
            "modalities": {"cam": "observation.images.cam_high", "joints": "observation.state"},
            "target": {"feature": "observation.state", "dims": [0, 1, 2]},
            "split": {"train": [0, 3], "val": [5]},
        }
    )
    dataset = open_quietly(config)
    assert cached_episodes(dataset) == [0, 3, 5]
    assert dataset.split_episodes == {"train": [0, 3], "val": [5], "test": []}
    assert dataset.presence["cam"].all()
    batch = next(iter(dataset.loader("val", batch_size=4)))
    assert batch.get(("obs", "cam")).shape == (4, 4, 3, 32, 32)
