"""The sealed protocol's selection stage of ``benchmarks/ethucy.py`` (``--select``): every option of a
fold chosen on its training scenes, each held out in turn, never on its test scene.

For the outer fold of test scene S and each of its four training scenes V, the models trained with S
and V held out (on the other three scenes' ``_train`` files, validated during training on their ``_val``
files) are scored on V's whole file, as the final stage scores S: the inner validation resembles the
test. Each model's candidate (the joint grid of the selected options it reads) with the lowest mean
all-modality minADE20 over the four is chosen; of equal means the one listed first. Constant velocity's
heading noise std is chosen the same way, with no training. An inner run is one pair's, so the outer
fold of V reuses it, scored on S (`benchmarks.pedestrians.selection`). Everything is recorded in
``<out>/<fold>/selection.json``.
"""

from __future__ import annotations

import argparse
import logging

from benchmarks.pedestrians.recipe import (
    CV_NOISE,
    HEADING_NOISE_GRID,
    PAPER,
    TRAINED,
    Budget,
    candidates,
    completed,
    data_config_path,
    recipe,
    run_path,
)
from benchmarks.pedestrians.runs import fold_config, scene_data, score, train_run, val_curve
from benchmarks.pedestrians.selection import (
    candidate_name,
    choose,
    held_out_pairs,
    inner_splits,
    mean_scores,
    pair_scenes,
)

logger = logging.getLogger("mmf_rl.benchmarks.ethucy")


def inner_run(args: argparse.Namespace, budget: Budget, pair: str, label: str, candidate: dict) -> dict:
    """The inner run of ``label`` with ``candidate``'s options and ``pair``'s scenes held out: reused,
    else trained (``scores.json`` written once trained; its held-out scenes' scores added as needed)."""
    from mmf_rl.eval.report import write_json

    if done := completed(args, pair, label, candidate):
        return done
    _, trained = train_run(args, budget, pair, label, candidate)
    run_dir = run_path(args, pair, label, candidate)
    result = {
        "recipe": recipe(args, budget, pair, label, candidate),
        "train_seconds": trained,
        "val_ade": val_curve(run_dir),
        "held_out": {},
    }
    write_json(run_dir / "scores.json", result)
    return result


def held_out_score(
    args: argparse.Namespace, pair: str, label: str, candidate: dict, scene: str, data
) -> float:
    """The inner run's all-modality minADE20 on ``scene`` (one of the pair), scored once and kept in
    its ``scores.json``; ``data()`` gives the scene's windows under the pair's training split."""
    from mmf_rl.eval.report import write_json
    from mmf_rl.models import load_trained_model

    run_dir = run_path(args, pair, label, candidate)
    result = completed(args, pair, label, candidate)
    if scene not in result["held_out"]:
        model, _, _ = load_trained_model(run_dir / "checkpoints", map_location=args.device)
        deterministic = label != PAPER
        result["held_out"][scene] = score(model, data(), "test", args, deterministic, modes=("all",))
        write_json(run_dir / "scores.json", result)
    return result["held_out"][scene]["all"]["min_ade_k"]


def pair_scene_data(args: argparse.Namespace, pair: str, scene: str):
    """``scene``'s windows (one of the pair) normalised with the pair's training split, as its models
    read them."""
    return scene_data(args, fold_config(args, pair), scene)


def inner_scores(args: argparse.Namespace, budget: Budget, fold: str) -> dict[str, dict[str, dict]]:
    """``{model: {candidate: {scene: minADE20}}}`` on ``fold``'s inner splits: each of its training scenes
    scored by the models trained with it and ``fold`` held out, trained first when needed."""
    from functools import cache, partial

    from mmf_rl.datasets.ethucy import FOLDS

    labels = [label for label in TRAINED if fold in budget.folds and candidates(args.select, label)]
    scores: dict[str, dict[str, dict]] = {label: {} for label in labels}
    for pair, scene in inner_splits(FOLDS, fold):
        # The scene's windows under the pair's training split: built once, and only if a run is still
        # to be scored on it.
        data = cache(partial(pair_scene_data, args, pair, scene))
        for label in labels:
            for candidate in candidates(args.select, label):
                inner_run(args, budget, pair, label, candidate)
                value = held_out_score(args, pair, label, candidate, scene, data)
                scores[label].setdefault(candidate_name(candidate), {})[scene] = value
    return scores


def held_out_heading_noise(args: argparse.Namespace, fold: str) -> dict[str, dict[str, float]]:
    """``{std: {scene: minADE20}}`` of constant velocity with heading noise on each of ``fold``'s
    training scenes, scored whole as a test scene is (no training: the fold's own config serves)."""
    from benchmarks.pedestrians.scoring import heading_noise_scores
    from mmf_rl.datasets.ethucy import FOLDS

    per_std: dict[str, dict[str, float]] = {str(sigma): {} for sigma in HEADING_NOISE_GRID}
    for _, scene in inner_splits(FOLDS, fold):
        data = scene_data(args, fold_config(args, fold), scene)
        on_scene = heading_noise_scores(data, HEADING_NOISE_GRID, args.batch_size, args.device, "test")
        for sigma, value in on_scene.items():
            per_std[str(sigma)][scene] = value
    return per_std


def write_held_out_configs(args: argparse.Namespace, budget: Budget) -> None:
    """The data config of each held-out pair the selection trains on (``--data/held_out/<a>+<b>.yaml``),
    from its two folds' configs: the training and val episodes both hold (every sequence's ``_train``
    and ``_val`` files but the pair's scenes'), no test episode. Written again each run: the same
    configs from the same conversion."""
    import yaml

    from mmf_rl.configuration import write_text_atomic
    from mmf_rl.datasets.ethucy import FOLDS

    for pair in held_out_pairs(FOLDS, budget.folds):
        a, b = (yaml.safe_load((args.data / f"{scene}.yaml").read_text()) for scene in pair_scenes(pair))
        split = {name: sorted(set(a["split"][name]) & set(b["split"][name])) for name in ("train", "val")}
        path = data_config_path(args, pair)
        path.parent.mkdir(exist_ok=True)
        config = yaml.safe_dump(a | {"split": split | {"test": []}}, sort_keys=False, default_flow_style=None)
        header = (
            f"# ETH/UCY with {' and '.join(pair_scenes(pair))} held out, written by bench ethucy --select\n"
        )
        write_text_atomic(path, header + config)


def select_fold(args: argparse.Namespace, budget: Budget, fold: str) -> tuple[dict, float]:
    """The selection stage of ``fold``: each trained model's options and the heading noise's std, chosen
    by the lowest mean minADE20 over ``fold``'s training scenes held out in turn, written to
    ``<out>/<fold>/selection.json``. Nothing here reads ``fold``'s own scene."""
    from mmf_rl.eval.report import write_json

    record = {"fold": fold, "options": args.select, "models": {}}
    chosen = {}
    for label, per_candidate in inner_scores(args, budget, fold).items():
        means = mean_scores(per_candidate)
        by_name = {candidate_name(c): c for c in candidates(args.select, label)}
        chosen[label] = by_name[choose(means)]
        record["models"][label] = {"inner_min_ade20": per_candidate, "mean": means, "chosen": chosen[label]}
    noise = held_out_heading_noise(args, fold)
    sigma = float(choose(mean_scores(noise)))
    record["models"][CV_NOISE] = {"inner_min_ade20": noise, "mean": mean_scores(noise), "chosen": sigma}
    (args.out / fold).mkdir(parents=True, exist_ok=True)
    write_json(args.out / fold / "selection.json", record)
    logger.info("%s selection: %s", fold, {label: r["chosen"] for label, r in record["models"].items()})
    return chosen, sigma
