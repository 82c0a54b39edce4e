"""The sealed protocol's arithmetic on synthetic scene names: which pairs are trained, which outer fold
reads which, that no inner run an outer fold reads touches its scene, and the choice."""

from itertools import combinations

import pytest

from benchmarks.pedestrians.selection import (
    candidate_name,
    choose,
    grid,
    held_out_pairs,
    inner_splits,
    is_pair,
    mean_scores,
    pair_name,
    pair_scenes,
    training_scenes,
)

SCENES = ("a", "b", "c", "d", "e")


def test_ten_pairs_train_every_three_scene_set_once():
    pairs = held_out_pairs(SCENES, SCENES)
    assert len(pairs) == 10
    trained_on = sorted(tuple(training_scenes(SCENES, pair)) for pair in pairs)
    assert trained_on == sorted(combinations(SCENES, 3))
    assert all(is_pair(pair) and not is_pair(pair_scenes(pair)[0]) for pair in pairs)


def test_a_pair_serves_both_its_folds_validated_on_the_other_scene():
    """The model trained on {a, b, c} serves fold d (validated on e) and fold e (validated on d)."""
    pair = pair_name("e", "d")
    assert pair == pair_name("d", "e") == "d+e"
    assert training_scenes(SCENES, pair) == ["a", "b", "c"]
    serves = {fold: scene for fold in SCENES for p, scene in inner_splits(SCENES, fold) if p == pair}
    assert serves == {"d": "e", "e": "d"}


@pytest.mark.parametrize("fold", SCENES)
def test_no_inner_run_of_a_fold_touches_its_scene(fold):
    splits = inner_splits(SCENES, fold)
    assert sorted(scene for _, scene in splits) == sorted(set(SCENES) - {fold})  # its four training scenes
    for pair, scene in splits:
        assert fold not in training_scenes(SCENES, pair)  # not trained on
        assert scene != fold  # not validated on
        assert sorted([*training_scenes(SCENES, pair), scene, fold]) == list(SCENES)


def test_folds_trained_on_some_scenes_need_only_the_pairs_holding_one_out():
    quick = held_out_pairs(SCENES, ["a", "b", "c"])
    assert len(quick) == 9 and pair_name("d", "e") not in quick
    assert held_out_pairs(SCENES, ["a"]) == ["a+b", "a+c", "a+d", "a+e"]
    assert {pair for fold in "abc" for pair, _ in inner_splits(SCENES, fold)} == set(quick)


def test_the_joint_grid_keeps_the_order_given_and_the_lower_mean_is_chosen_ties_to_the_first():
    candidates = grid({"rotation": ["0", "180"], "sampler": ["5/5", "20/10"]})
    assert [candidate_name(c) for c in candidates] == [
        "rotation=0 sampler=5/5",
        "rotation=0 sampler=20/10",
        "rotation=180 sampler=5/5",
        "rotation=180 sampler=20/10",
    ]
    assert grid({}) == [{}]
    means = mean_scores({"x": {"b": 0.4, "c": 0.2}, "y": {"b": 0.2, "c": 0.3}})
    assert means == pytest.approx({"x": 0.3, "y": 0.25})
    assert choose(means) == "y"
    assert choose({"first": 0.25, "second": 0.25, "third": 0.3}) == "first"
