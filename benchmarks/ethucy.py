"""ETH/UCY pedestrians: the paper model vs the baselines, leave one scene out, in metres.

    .venv/bin/python benchmarks/ethucy.py --quick      # 3 folds, short training (QUICK)
    .venv/bin/python benchmarks/ethucy.py              # the 5 folds (FULL)
    .venv/bin/python benchmarks/ethucy.py --seed 1 --out runs/bench_ethucy_seed1   # another training seed
    .venv/bin/python benchmarks/ethucy.py --seeds 0 1 2 --out runs/bench_ethucy_seeds   # over 3 seeds
    .venv/bin/python benchmarks/ethucy.py --window-set social_gan --out runs/bench_ethucy_sgan
    mmf-rl bench ethucy --quick --out runs/bench_ethucy_quick
    mmf-rl bench ethucy --select augment=lerobot,none --select augment.rotation=0,180 \
        --select sampler=5/5,20/10 --out runs/bench_ethucy_sealed      # the sealed protocol

For each fold (its test scene held out; train/val from the other scenes' ``_train``/``_val`` files):
the paper model (the attention CVAE with ``model.prior=learned``; the fold's data config: ``deepsets``
neighbours, conv scene), LF-LSTM and MulT are trained ONCE on all modalities, their scene crops
through lerobot's default image transforms (``augment=lerobot``) and every training window turned by
a random angle (``augment.rotation=180``); the baselines see an absent modality as zeros (the
zero-fill protocol of the push accuracy benchmark); constant velocity and constant velocity with
sampled heading noise (its angle std chosen on the fold's val split) need no training. The paper
model's 20 samples are the codes of a learned sampler (DLow, which AgentFormer's published numbers
use too: ``model.learned_samples=20``, trained after the forecaster with the forecaster frozen,
``sampler.steps``); the row ``paper model, prior samples`` scores the same weights with 20 draws
from ``p(z | X)``. Every model is scored in four modes (all modalities, without ``scene``, without
``neighbours``, trajectory only) on the same test windows: ADE/FDE of the point forecast and
minADE20/minFDE20 per agent over 20 samples
(:mod:`benchmarks.pedestrians.scoring`).

The recipe's options (`benchmarks.pedestrians.recipe.OPTIONS`: the image augmentation, the rotation of
training windows, the learned sampler's diversity) were chosen while test scenes were printed: given by
hand, a row is a *probe* that has seen the test. ``--select OPTION=V1,V2`` (repeated) runs the *sealed*
protocol (`benchmarks.pedestrians.sealed`): before a fold's final stage, each of its four training
scenes is held out in turn and each model's candidates (the joint grid of the selected options it
reads) are trained on the other three scenes at the invocation's budget and scored on the held-out
scene's whole file; the lowest mean all-modality minADE20 is chosen (of equal means, the value listed
first), and so is constant velocity's heading noise std. The test scene is read only by the final
stage, once. A model trained with two scenes held out serves both their folds: a candidate costs ten
trainings for the five folds. ``<out>/<fold>/selection.json`` records the candidates, the inner scores
and the choices; every trained row records its protocol (``sealed`` when every option it reads was
selected, else ``probe``), its candidates and its choice in its recipe.

``--window-set`` chooses the val and test windows every row is scored on, as the literature does in
two ways (``mmf_rl.datasets.ethucy.WINDOW_SETS``): ``trajectron`` (the default), every window of 20
annotated steps of one person, as Trajectron++ and AgentFormer score; ``social_gan``, only those
another person is annotated in throughout, as Social-GAN and Social-STGCNN score. A published figure
compares with a row on its own set only. The models train on every window of the training split
either way.

The data is converted into ``--data`` when its fold configs are absent (``mmf-rl import ethucy``);
the window cache is built once for all folds (``--data``/cache). Completed runs
(``<out>/<fold>/<model>/scores.json``, the selection's ``<out>/select/<pair>/<model>/<values>/``) are
reused, so an interrupted benchmark resumes; delete
``--out`` to start over. Each ``scores.json`` records its recipe (a trained model's training
overrides, a constant-velocity row's heading noise grid, the window set:
`benchmarks.pedestrians.recipe`), and before anything runs a completed run whose recipe differs from
this invocation's (another mode or window set, or a recipe changed since), or records none, is
refused with the settings that differ: train it into another ``--out``, or delete its directory to
compute it again. Writes ``<out>/results.md``,
``<out>/results.json`` and one figure per fold (``<out>/<fold>/forecasts.png``), and ends with one
line:
``summary: paper model minADE20/minFDE20 avg A/F (without scene A/F, without neighbours A/F);
constant velocity A/F; best baseline NAME A/F (MODE; window set WINDOW_SET; PROTOCOL)``, PROTOCOL
``sealed`` or ``probe, seen test: OPTION=VALUE, ... given by hand``. ``--seeds N ...`` runs each seed
as ``--seed N --out <out>/seed<N>`` does (completed runs reused), then writes ``<out>/results.{md,json}``
with, per scene and of each average over scenes (the per-seed averages'), the mean and the range
(max - min: with three seeds no std is claimed) over the seeds, and the seeds' summary lines; its line:
``summary: paper model minADE20/minFDE20 avg A/F ±a/f over seeds 0,1,2 (without scene A/F ±a/f, without
neighbours A/F ±a/f); constant velocity A/F; best baseline NAME A/F ±a/f (MODE; window set WINDOW_SET;
PROTOCOL; ± range: max - min over the seeds)``, each A/F a mean over the seeds, each a/f its range.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.pedestrians.recipe import (
    CV,
    CV_NOISE,
    FULL,
    HEADING_NOISE_GRID,
    NUM_SAMPLES,
    OPTIONS,
    PAPER,
    PAPER_PRIOR,
    QUICK,
    TRAINED,
    Budget,
    check_reused,
    completed,
    constant_velocity_recipe,
    given_by_hand,
    options_read,
    parse_select,
    protocol,
    recipe,
    recipe_differences,
    run_path,
    slug,
)
from benchmarks.pedestrians.runs import fold_data, score, train_run, val_curve
from benchmarks.pedestrians.sealed import select_fold, write_held_out_configs

REPO = Path(__file__).resolve().parents[1]
# Under mmf_rl, so that the library's logging setup (`mmf-rl bench`, or this script's own) shows it; a
# handler of its own on the root logger would print every library message a second time.
logger = logging.getLogger("mmf_rl.benchmarks.ethucy")
DETERMINISTIC = ("LF-LSTM", "MulT", CV)
FIGURE_WINDOWS = 4


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from mmf_rl.datasets.ethucy import WINDOW_SETS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 folds, short training (QUICK)")
    parser.add_argument("--raw", type=Path, default=REPO.parent / "shared" / "data" / "ethucy")
    parser.add_argument("--data", type=Path, default=REPO / "data" / "ethucy", help="converted dataset")
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "bench_ethucy")
    seeds = parser.add_mutually_exclusive_group()
    seeds.add_argument(
        "--seed", type=int, default=0, help="training seed of every model (another seed: another --out)"
    )
    seeds.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        metavar="N",
        help="run the benchmark once per seed into <out>/seed<N> (each as --seed N --out <out>/seed<N>), "
        "then write the mean and the range (max - min) over the seeds per scene and of the average",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch-size", type=int, default=512, help="evaluation batch size")
    parser.add_argument(
        "--window-set",
        choices=sorted(WINDOW_SETS),
        default="trajectron",
        help="the val and test windows every row is scored on: trajectron, every window of 20 annotated "
        "steps (Trajectron++, AgentFormer); social_gan, those another person is annotated in throughout "
        "(Social-GAN, Social-STGCNN). The models train on every training window either way; another "
        "window set: another --out",
    )
    parser.add_argument(
        "--select",
        action="append",
        default=[],
        metavar="OPTION=V1,V2",
        help="the sealed protocol: choose OPTION per fold among the values, on the fold's training scenes "
        "each held out in turn (trained on the other three), never on its test scene; repeat for several "
        "options (their joint grid is tried; a tie goes to the value listed first). Options: "
        + "; ".join(f"{name} (given by hand: {option.default})" for name, option in OPTIONS.items())
        + ". A model some of whose options are given by hand is a probe",
    )
    args = parser.parse_args(argv)
    if args.seeds and len(set(args.seeds)) < len(args.seeds):
        parser.error(f"--seeds: a seed given twice: {' '.join(map(str, args.seeds))}")
    try:
        args.select = parse_select(args.select)
    except ValueError as error:
        parser.error(str(error))
    return args


def ensure_data(args: argparse.Namespace, folds: tuple[str, ...]) -> float:
    """Convert the raw files when a fold's data config is absent; returns the wall time."""
    from mmf_rl.datasets import ethucy

    if all((args.data / f"{fold}.yaml").is_file() for fold in folds):
        for fold in folds:
            check_planar_declared(args.data / f"{fold}.yaml")
        return 0.0
    start = time.perf_counter()
    ethucy.convert(args.raw, sorted(ethucy.FOLDS), args.data)
    return time.perf_counter() - start


def check_planar_declared(path: Path) -> None:
    """A fold config converted before the converter declared the planar dims cannot be turned."""
    import yaml

    if not yaml.safe_load(path.read_text())["target"].get("planar"):
        raise SystemExit(
            f"{path} was converted by an older mmf-rl: it does not declare the planar dims that "
            "augment.rotation turns; convert again into a new --data (or delete this one)"
        )


def prior_scores(model, data, args: argparse.Namespace) -> dict:
    """The paper model's scores with 20 draws from its prior instead of its learned sampler's codes."""
    with model.drawing_from_the_prior():
        return score(model, data, "test", args)


def run_trained(
    args: argparse.Namespace,
    budget: Budget,
    fold: str,
    label: str,
    data,
    chosen: dict[str, str] | None = None,
) -> dict:
    """Train one model on the fold (its options ``chosen``'s or given by hand), score it on the test
    scene; ``scores.json`` written last."""
    from mmf_rl.eval.report import write_json

    start = time.perf_counter()
    model, trained = train_run(args, budget, fold, label, chosen)
    run_dir = run_path(args, fold, label)
    result = {
        "scores": score(model, data, "test", args, deterministic=label != PAPER),
        **({"prior_scores": prior_scores(model, data, args)} if label == PAPER else {}),
        "recipe": recipe(args, budget, fold, label, chosen),
        "train_seconds": trained,
        "val_ade": val_curve(run_dir),
    }
    result["seconds"] = time.perf_counter() - start
    write_json(run_dir / "scores.json", result)
    logger.info(
        "%s %s: trained in %.0f s, scored in %.0f s", fold, label, trained, result["seconds"] - trained
    )
    return result


def reused(args: argparse.Namespace, budget: Budget, fold: str, label: str, chosen) -> dict | None:
    """A completed row to reuse, None: none. Before the selection ran, a row was checked with the choice
    it records; one the selection would now choose otherwise (its inner runs computed again) is refused."""
    done = completed(args, fold, label)
    if done and (
        differences := recipe_differences(recipe(args, budget, fold, label, chosen), done["recipe"])
    ):
        raise SystemExit(
            f"ethucy: {run_path(args, fold, label)} was trained with another choice than the selection "
            f"makes now: {'; '.join(differences)}; delete it to train it with this one (nothing was deleted)"
        )
    return done


def run_constant_velocity(
    args: argparse.Namespace, fold: str, data, sigma: float | None = None
) -> dict[str, dict]:
    """Both constant-velocity rows; the sampler's angle std ``sigma`` (the selection stage's), else the
    val split's best minADE20."""
    from benchmarks.pedestrians.scoring import best_heading_noise, constant_velocity_model
    from mmf_rl.eval.report import write_json

    results = {}
    run_dir = args.out / fold / slug(CV)
    start = time.perf_counter()
    results[CV] = {
        "scores": score(constant_velocity_model(data, 0.0), data, "test", args, deterministic=True),
        "recipe": constant_velocity_recipe(args, CV),
    }
    results[CV]["seconds"] = time.perf_counter() - start
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(run_dir / "scores.json", results[CV])
    start = time.perf_counter()
    on_val = {}  # with sigma given, its evidence is the selection's (selection.json)
    if sigma is None:
        sigma, scores = best_heading_noise(data, HEADING_NOISE_GRID, args.batch_size, args.device)
        on_val = {"val_min_ade_k": scores}
    results[CV_NOISE] = {
        "scores": score(constant_velocity_model(data, sigma), data, "test", args),
        "heading_noise": sigma,
        "recipe": constant_velocity_recipe(args, CV_NOISE),
        **on_val,
        "seconds": time.perf_counter() - start,
    }
    (args.out / fold / slug(CV_NOISE)).mkdir(parents=True, exist_ok=True)
    write_json(args.out / fold / slug(CV_NOISE) / "scores.json", results[CV_NOISE])
    return results


def draw_fold(args: argparse.Namespace, fold: str, data) -> Path:
    """The paper model's 20 samples, the ground truth and the observed past of a few test agents,
    on the test scene's reference frame through its world->pixel map."""
    from benchmarks.pedestrians.scoring import draw_test_samples
    from mmf_rl.datasets import ethucy
    from mmf_rl.models import load_trained_model

    model, _, _ = load_trained_model(args.out / fold / slug(PAPER) / "checkpoints", map_location="cpu")
    scene = ethucy.load_scene(args.raw, ethucy.SCENE_OF[ethucy.FOLDS[fold][0]])
    title = (
        f"{fold}: paper model, {NUM_SAMPLES} learned samples (orange), ground truth (green), "
        "observed 8 steps (white)"
    )
    path = args.out / fold / "forecasts.png"
    return draw_test_samples(model, data, FIGURE_WINDOWS, scene, path, title, NUM_SAMPLES)


def run_fold(args: argparse.Namespace, budget: Budget, fold: str) -> dict[str, dict]:
    """Every model's scores on the fold: the trained ones only in ``budget.folds``. With ``--select``,
    the selection stage first, then the final stage, the only one that reads the fold's test scene."""
    chosen, sigma = select_fold(args, budget, fold) if args.select else ({}, None)
    data, _ = fold_data(args, fold)
    results = {}
    for label in TRAINED if fold in budget.folds else ():
        choice = chosen.get(label)
        results[label] = reused(args, budget, fold, label, choice) or run_trained(
            args, budget, fold, label, data, choice
        )
    if PAPER in results:
        results[PAPER_PRIOR] = {"scores": results[PAPER]["prior_scores"]}
    if completed(args, fold, CV) and completed(args, fold, CV_NOISE):
        results |= {label: completed(args, fold, label) for label in (CV, CV_NOISE)}
    else:
        results |= run_constant_velocity(args, fold, data, sigma)
    if fold in budget.folds and not (args.out / fold / "forecasts.png").is_file():
        draw_fold(args, fold, data)
    return results


def protocol_summary(args: argparse.Namespace, budget: Budget) -> str:
    """The summary line's protocol: ``sealed``, or ``probe, seen test: OPTION=VALUE ... given by hand``."""
    given = given_by_hand(args, TRAINED if budget.folds else ())
    return f"probe, seen test: {', '.join(given)} given by hand" if given else "sealed"


def average_section(title: str, average: dict) -> list[str]:
    from benchmarks.pedestrians.scoring import relative_rise, scores_table

    note = (
        "† deterministic: its 20 samples are equal, so minADE20/minFDE20 = ADE/FDE. Metres; 8 observed / "
        "12 forecast steps; every mode on the same test windows."
    )
    rises = "; ".join(
        f"{m}: without scene {relative_rise(average[m], 'without_scene'):+.0%}, without neighbours "
        f"{relative_rise(average[m], 'without_neighbours'):+.0%}"
        for m in (PAPER, PAPER_PRIOR, "LF-LSTM", "MulT")
        if m in average
    )
    lines = [f"## {title}\n", scores_table(average, DETERMINISTIC), "", note, ""]
    return lines + ([f"minADE20 rise against all modalities: {rises}.\n"] if rises else [])


def protocol_section(args: argparse.Namespace, budget: Budget) -> tuple[str, ...]:
    """The page's protocol: for each trained model, sealed (every option it reads chosen on held-out
    training scenes) or a probe (some given by hand, chosen while the test scenes were printed)."""
    lines = ["## Protocol\n"]
    for label in TRAINED if budget.folds else ():
        read = options_read(label)
        if protocol(args, label) == "sealed":
            status = f"sealed: {', '.join(read)} chosen per fold on its training scenes held out in turn"
        else:
            status = f"probe, seen test: {', '.join(given_by_hand(args, [label]))} given by hand"
        lines.append(f"- {label}: {status}")
    where = "the fold's training scenes held out" if args.select else "the fold's val split"
    lines.append(f"- {CV_NOISE}: its std chosen on {where}")
    selection = "; the candidates, inner scores and choices in `<fold>/selection.json`" if args.select else ""
    return (*lines, f"\nOptions: {', '.join(OPTIONS)}{selection}.\n")


def choice_text(rows: dict) -> str:
    """``model: option=value ...`` of each row the selection chose for, from the recipes it records."""
    chosen = {
        label: " ".join(s.removeprefix("chosen.") for s in row.get("recipe", []) if s.startswith("chosen."))
        for label, row in rows.items()
    }
    return "; ".join(f"{label}: {text}" for label, text in chosen.items() if text)


def heading_noise_text(row: dict) -> str:
    """The heading noise's std of a fold and where it was chosen (rows recorded before: on val)."""
    settings = dict(setting.split("=", 1) for setting in row.get("recipe", []))
    held_out = settings.get("heading_noise_chosen_on") == "held_out_scenes"
    where = "the held-out training scenes" if held_out else "val"
    return f"heading noise std {row['heading_noise']} rad, chosen on {where}"


def markdown(
    per_fold: dict,
    averages: dict[str, dict],
    budget: Budget,
    window_set: str,
    seconds: dict,
    protocol_lines: tuple[str, ...] = (),
) -> str:
    from benchmarks.pedestrians.scoring import published_table, scores_table
    from mmf_rl.datasets.ethucy import WINDOW_SETS

    parts = [f"# ETH/UCY ({budget.name})\n"]
    parts += [
        f"Every row is scored on the `{window_set}` window set: {WINDOW_SETS[window_set]}. The models "
        "train on every window of the training split.\n"
    ]
    parts += protocol_lines
    for title, average in averages.items():
        parts += average_section(title, average)
    for fold, rows in per_fold.items():
        scores = {label: r["scores"] for label, r in rows.items()}
        windows = int(scores[CV]["all"]["windows"])
        parts += [f"## {fold} ({windows} test windows; {heading_noise_text(rows[CV_NOISE])})\n"]
        parts += [f"Chosen on the held-out training scenes: {text}.\n"] if (text := choice_text(rows)) else []
        parts += [scores_table(scores, DETERMINISTIC), ""]
        parts += [f"![forecasts]({fold}/forecasts.png)\n"] if fold in budget.folds else []
    parts += ["## Published (minADE20 / minFDE20, average of the 5 scenes, on their window set)\n"]
    parts += [published_table(), ""]
    parts += [f"Wall time in s (upper bounds: a shared, loaded machine): {json.dumps(seconds)}\n"]
    return "\n".join(parts)


def run_seed(args: argparse.Namespace) -> tuple[dict, str]:
    """The benchmark of one seed (``args.seed``) into ``args.out``: its results (as ``results.json``
    holds them) and its summary line, both written and the line printed."""
    from benchmarks.pedestrians.scoring import summary_line
    from mmf_rl.datasets import ethucy
    from mmf_rl.eval.report import write_json, write_text

    budget = QUICK if args.quick else FULL
    check_reused(args, budget, ethucy.FOLDS)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    seconds = {"convert": ensure_data(args, tuple(ethucy.FOLDS))}
    if args.select:
        write_held_out_configs(args, budget)
    per_fold = {}
    for fold in sorted(ethucy.FOLDS):
        fold_start = time.perf_counter()
        per_fold[fold] = run_fold(args, budget, fold)
        seconds[fold] = round(time.perf_counter() - fold_start)
    seconds["total"] = round(time.perf_counter() - start)
    scores = fold_scores(per_fold)
    averages = averages_of(scores, budget, args.window_set)
    average = next(iter(averages.values()))
    summary = summary_line(average, PAPER, CV, BASELINES, run_text(args, budget))
    results = {
        "mode": budget.name,
        "window_set": args.window_set,
        "protocol": {label: protocol(args, label) for label in TRAINED if budget.folds},
        "select": args.select,
        "folds": per_fold,
        "averages": averages,
        "seconds": seconds,
        "summary": summary,
    }
    write_json(args.out / "results.json", results)
    page = markdown(per_fold, averages, budget, args.window_set, seconds, protocol_section(args, budget))
    write_text(args.out / "results.md", page + f"\n{summary}\n")
    print(summary)
    return results, summary


BASELINES = ["LF-LSTM", "MulT", CV, CV_NOISE]


def fold_scores(per_fold: dict) -> dict[str, dict[str, dict]]:
    """``{fold: {model: scores}}`` of ``{fold: {model: row}}`` (a row as ``results.json`` holds it)."""
    return {fold: {model: row["scores"] for model, row in rows.items()} for fold, rows in per_fold.items()}


def averages_of(scores: dict, budget: Budget, window_set: str) -> dict[str, dict]:
    """``{title: average over scenes}``: the trained folds' first, then (folds without trained rows)
    constant velocity's over the five scenes."""
    from benchmarks.pedestrians.scoring import average_over_scenes

    trained = f"Average over the trained folds ({', '.join(budget.folds)})"
    averages = {trained: average_over_scenes(scores, budget.folds)}
    if set(budget.folds) != set(scores):
        check = f"Constant velocity, average over the 5 scenes (the protocol check, {window_set} windows)"
        averages[check] = average_over_scenes(scores)
    return averages


def run_text(args: argparse.Namespace, budget: Budget) -> str:
    """The summary line's run: mode, window set, protocol."""
    return f"{budget.name}; window set {args.window_set}; {protocol_summary(args, budget)}"


def seed_run_args(args: argparse.Namespace, seed: int) -> argparse.Namespace:
    """``args`` of the one-seed run ``--seed seed --out <out>/seed<seed>``."""
    return argparse.Namespace(**{**vars(args), "seed": seed, "seeds": None, "out": args.out / f"seed{seed}"})


def run_seeds(args: argparse.Namespace) -> str:
    """Each of ``args.seeds``'s benchmark into ``<out>/seed<N>`` (completed ones reused), then their
    mean and range per scene and of each average over scenes into ``<out>/results.{json,md}``; returns
    the summary line."""
    from benchmarks.pedestrians.scoring import summary_line
    from benchmarks.pedestrians.seeds import SPREAD, over_seeds, per_scene_over_seeds, statistic
    from mmf_rl.eval.report import write_json, write_text

    runs = {seed: run_seed(seed_run_args(args, seed)) for seed in args.seeds}
    scores = {seed: fold_scores(results["folds"]) for seed, (results, _) in runs.items()}
    folds = per_scene_over_seeds(scores)
    titles = list(runs[args.seeds[0]][0]["averages"])
    averages = {t: over_seeds({seed: r["averages"][t] for seed, (r, _) in runs.items()}) for t in titles}
    average = averages[titles[0]]
    budget = QUICK if args.quick else FULL
    run = f"{run_text(args, budget)}; ± {SPREAD}"
    summary = summary_line(
        statistic(average, "mean"), PAPER, CV, BASELINES, run, statistic(average, "range"), args.seeds
    )
    per_seed = {seed: line for seed, (_, line) in runs.items()}
    args.out.mkdir(parents=True, exist_ok=True)
    results = {"seeds": args.seeds, "spread": SPREAD, "summaries": per_seed, "folds": folds}
    write_json(args.out / "results.json", results | {"averages": averages, "summary": summary})
    write_text(args.out / "results.md", seeds_markdown(args, budget, folds, averages, per_seed, summary))
    print(summary)
    return summary


def seeds_markdown(args, budget: Budget, folds: dict, averages: dict, per_seed: dict, summary: str) -> str:
    """The page of a run over seeds: each average's and each scene's mean (range) table, each seed's
    summary line, the summary over the seeds."""
    from benchmarks.pedestrians.seeds import seeds_table

    seeds = ", ".join(map(str, args.seeds))
    parts = [f"# ETH/UCY ({budget.name}), over training seeds {seeds}\n"]
    parts += [
        f"Each cell: the mean over the seeds, then in brackets the range (max - min over the seeds; with "
        f"{len(args.seeds)} seeds no std is claimed). An average over scenes: each seed's own average, its "
        f"range that of the per-seed averages. Window set `{args.window_set}`; each seed's page: "
        "`seed<N>/results.md`.\n"
    ]
    for title, stats in averages.items():
        parts += [f"## {title}\n", seeds_table(stats, DETERMINISTIC), ""]
    for fold, stats in folds.items():
        parts += [f"## {fold}\n", seeds_table(stats, DETERMINISTIC), ""]
    parts += ["## Each seed\n", *(f"- seed {seed}: `{line}`" for seed, line in per_seed.items()), ""]
    return "\n".join(parts) + f"\n{summary}\n"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.seeds:
        run_seeds(args)
    else:
        run_seed(args)
    return 0


if __name__ == "__main__":
    from mmf_rl.log import configure_logging

    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    raise SystemExit(main())
