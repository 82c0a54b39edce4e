"""mmf_rl.compare.bootstrap: the paired bootstrap over test episodes (or blocks of windows), "best or
tied", the table's subset order."""

from __future__ import annotations

import pytest
import torch

from mmf_rl.compare import bootstrap
from tests.compare.helpers import PAPER_SUBSETS, PUSH_SUBSETS, cell, rows


def windows(num_episodes: int = 8, per_episode: int = 5, seed: int = 0, scale: float = 1.0):
    """(episode of each window, squared errors) with episode-dependent levels, as a test split gives."""
    g = torch.Generator().manual_seed(seed)
    episodes = [e for e in range(num_episodes) for _ in range(per_episode)]
    level = torch.rand(num_episodes, generator=g)[torch.tensor(episodes)]
    return episodes, (scale * level * (1 + 0.1 * torch.rand(len(episodes), generator=g))).tolist()


def test_episode_totals_sum_per_episode_in_the_given_order():
    sums, counts = bootstrap.episode_totals([3, 1, 3, 3], [1.0, 2.0, 3.0, 4.0], order=[1, 3, 5])
    assert sums.tolist() == [2.0, 8.0, 0.0]
    assert counts.tolist() == [1.0, 3.0, 0.0]
    with pytest.raises(ValueError, match=r"episodes \[7\]"):
        bootstrap.episode_totals([7], [1.0], order=[1, 3])


def test_bootstrap_weights_resample_episodes_with_replacement_from_one_seed():
    weights = bootstrap.bootstrap_weights(6, resamples=50, seed=3)
    assert weights.shape == (50, 6)
    assert torch.all(weights.sum(1) == 6)
    assert torch.equal(weights, bootstrap.bootstrap_weights(6, resamples=50, seed=3))
    assert not torch.equal(weights, bootstrap.bootstrap_weights(6, resamples=50, seed=4))
    assert (weights == 0).any() and (weights > 1).any()  # some episodes left out, some drawn twice


def test_cell_mean_is_the_seed_mean_of_window_means_and_the_interval_holds_it():
    order = list(range(8))
    weights = bootstrap.bootstrap_weights(8, resamples=500)
    seeds = [windows(seed=s) for s in (0, 1, 2)]
    c = bootstrap.bootstrap_cell([bootstrap.episode_totals(e, err, order) for e, err in seeds], weights)
    expected = sum(sum(err) / len(err) for _, err in seeds) / 3
    assert c.mean == pytest.approx(expected)
    assert c.per_seed == pytest.approx([sum(err) / len(err) for _, err in seeds])
    assert c.windows == 40
    assert c.low < c.mean < c.high
    # Episode-level variation dominates, so the interval is far wider than the within-episode noise.
    assert c.high - c.low > 0.05


def test_constant_errors_give_a_zero_width_interval():
    episodes = [e for e in range(5) for _ in range(3)]
    c = bootstrap.bootstrap_cell(
        [bootstrap.episode_totals(episodes, [0.3] * 15, range(5))],
        bootstrap.bootstrap_weights(5, resamples=100),
    )
    assert c.low == pytest.approx(0.3) and c.high == pytest.approx(0.3)


def test_the_bootstrap_is_paired_across_entries():
    """An entry that is worse by exactly 0.01 on every window is worse by 0.01 on every resample:
    the paired difference interval is a point, although both marginal intervals are wide."""
    order = list(range(8))
    weights = bootstrap.bootstrap_weights(8, resamples=300)
    episodes, errors = windows()
    a = bootstrap.bootstrap_cell([bootstrap.episode_totals(episodes, errors, order)], weights)
    b = bootstrap.bootstrap_cell(
        [bootstrap.episode_totals(episodes, [x + 0.01 for x in errors], order)], weights
    )
    assert bootstrap.overlap(a, b)
    low, high = bootstrap.difference_interval(b, a)
    assert low == pytest.approx(0.01) and high == pytest.approx(0.01)


def test_seeds_scored_on_different_windows_are_refused():
    weights = bootstrap.bootstrap_weights(2, resamples=10)
    with pytest.raises(ValueError, match="different test windows"):
        bootstrap.bootstrap_cell(
            [
                bootstrap.episode_totals([0, 1], [1.0, 1.0], [0, 1]),
                bootstrap.episode_totals([0], [1.0], [0, 1]),
            ],
            weights,
        )


def test_best_or_tied_is_decided_by_overlapping_intervals():
    cells = {"paper": cell(0.30, 0.27, 0.33), "rival": cell(0.28, 0.25, 0.31), "far": cell(0.5, 0.45, 0.55)}
    assert bootstrap.best_or_tied(cells, "paper")  # worse mean, intervals overlap: tied
    assert not bootstrap.best_or_tied(cells, "far")
    assert bootstrap.best_or_tied(cells, "rival")
    cells["rival"] = cell(0.20, 0.18, 0.22)
    assert not bootstrap.best_or_tied(cells, "paper")


def test_headline_subsets_lead_the_table():
    assert bootstrap.ordered_subsets(PUSH_SUBSETS, lead=PAPER_SUBSETS) == [
        "all",
        "without_proprio",
        "without_force",
        "without_image",
        "only_force",
        "only_image",
        "only_proprio",
    ]
    assert bootstrap.ordered_subsets(PUSH_SUBSETS) == PUSH_SUBSETS


def test_blocks_are_consecutive_test_windows_of_one_episode_and_the_same_in_every_row():
    # Episode 7's test windows are 100..144, episode 9's 200..209; one subset lost windows 100 and 101.
    full = rows([*range(100, 145), *range(200, 210)], [7] * 45 + [9] * 10)
    partial = rows(list(range(102, 145)), [7] * 43)
    errors = {"paper": {"all": [full], "only_state": [partial]}, "MulT": {"all": [dict(full)]}}
    assert bootstrap.bootstrap_unit(errors, block=20) == "block"
    blocks = full["block"]
    assert blocks[:20] == [(7, 0)] * 20 and blocks[20:40] == [(7, 1)] * 20 and blocks[40:45] == [(7, 2)] * 5
    assert blocks[45:] == [(9, 0)] * 10  # a block never crosses episodes
    assert partial["block"] == blocks[2:45]  # numbered from the episode's first window in any row
    assert errors["MulT"]["all"][0]["block"] == blocks


def test_enough_test_episodes_are_resampled_as_episodes():
    episodes = list(range(bootstrap.MIN_EPISODES))
    errors = {"paper": {"all": [rows([10 * e for e in episodes], episodes)]}}
    assert bootstrap.bootstrap_unit(errors, block=20) == "episode"
    assert "block" not in errors["paper"]["all"][0]


def test_block_bootstrap_gives_an_interval_where_one_episode_gives_none():
    """One test episode: an episode bootstrap has a zero-width interval; blocks give a real one."""
    g = torch.Generator().manual_seed(0)
    errors = (torch.linspace(0.2, 2.0, 100) * (1 + 0.1 * torch.rand(100, generator=g))).tolist()
    subsets = ["all", "only_state"]
    per_subset = {s: [rows(list(range(100)), [4] * 100, errors)] for s in subsets}
    episode_table, _ = bootstrap.build_table({"paper": per_subset}, {"paper": "paper"}, subsets)
    c = episode_table.cells["paper"]["all"]
    assert c.low == pytest.approx(c.high)
    unit = bootstrap.bootstrap_unit({"paper": per_subset}, block=20)
    table, groups = bootstrap.build_table({"paper": per_subset}, {"paper": "paper"}, subsets, unit=unit)
    assert len(groups) == 5
    c = table.cells["paper"]["all"]
    assert c.mean == pytest.approx(sum(errors) / 100)
    assert c.low < c.mean < c.high
