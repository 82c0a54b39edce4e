"""ETH/UCY pedestrians: the paper model vs the baselines, leave one scene out, in metres.

    .venv/bin/python benchmarks/ethucy.py --quick      # 3 folds, short training (see QUICK)
    .venv/bin/python benchmarks/ethucy.py              # the 5 folds (see FULL)
    .venv/bin/python benchmarks/ethucy.py --seed 1 --out runs/bench_ethucy_seed1   # another training seed
    mmf-rl bench ethucy --quick --out runs/bench_ethucy_quick

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
(:mod:`mmf_rl.eval.trajectories`).

The data is converted into ``--data`` when its fold configs are absent (``mmf-rl import ethucy``);
the window cache is built once for all folds (``--data``/cache). Completed runs
(``<out>/<fold>/<model>/scores.json``) are reused, so an interrupted benchmark resumes; delete
``--out`` to start over. Each ``scores.json`` records its recipe (a trained model's training
overrides, a constant-velocity row's heading noise grid), and before anything runs a completed run
whose recipe differs from this invocation's (another mode, or a recipe changed in this file since),
or records none, is refused with the settings that differ: train it into another ``--out``, or delete
its directory to compute it again. Writes ``<out>/results.md``, ``<out>/results.json`` and one figure per
fold (``<out>/<fold>/forecasts.png``), and ends with one line:
``summary: paper model minADE20/minFDE20 avg A/F (without scene A/F, without neighbours A/F);
constant velocity A/F; best baseline NAME A/F (MODE)``.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import torch

# Under mmf_rl, so that the library's logging setup (`mmf-rl bench`, or this script's own) shows it; a
# handler of its own on the root logger would print every library message a second time.
logger = logging.getLogger("mmf_rl.benchmarks.ethucy")
REPO = Path(__file__).resolve().parents[1]
NUM_SAMPLES = 20  # the K of minADE20 / minFDE20
PAPER, CV, CV_NOISE = "paper model", "constant velocity", "constant velocity + heading noise"
PAPER_PRIOR = "paper model, prior samples"  # the paper model's weights, 20 draws from p(z | X)
TRAINED = {  # label -> model overrides
    PAPER: ("model=forecaster", "model.prior=learned", f"model.learned_samples={NUM_SAMPLES}"),
    "LF-LSTM": ("model=lf_lstm",),
    "MulT": ("model=mult",),
}
# Every trained model sees its scene crops through lerobot's default image transforms: trained on four
# fixed reference frames, a model can learn their look (light, colour, sharpness), which the held-out
# scene's frame does not share. And each training window is turned by a random angle (trajectories,
# neighbours, target and the north-up crop together), as Trajectron++ trains on these files: otherwise
# a model learns the training scenes' walking directions, which the held-out scene need not share.
AUGMENT = ("augment=lerobot", "augment.rotation=180")
# The learned sampler's diversity: AgentFormer's setting for hotel, zara1 and zara2. On the five folds'
# validation scenes it ties its univ setting (10 / 10) and beats its eth one (20 / 10) (docs/results.md).
# Named here so that a run trained with other weights is never reused.
SAMPLER = ("sampler.diversity_weight=5.0", "sampler.diversity_scale=5.0")
DETERMINISTIC = ("LF-LSTM", "MulT", CV)
HEADING_NOISE_GRID = (0.05, 0.1, 0.15, 0.2, 0.3, 0.45)  # radians, the sampler's std picked on val
# The constant-velocity rows' recipes (see ``recipe``): they are computed together, from no training.
CV_RECIPES = {CV: ["heading_noise=0.0"], CV_NOISE: [f"heading_noise_grid={list(HEADING_NOISE_GRID)}"]}
FIGURE_WINDOWS = 4


# Scene crops are resized to this side in the window cache: the baselines run their ConvNet on every
# frame (the paper model stacks the 8 frames), which at the converter's 64 px made their training
# and scoring most of the benchmark's time on 2 cores (docs/results.md).
IMAGE_SIZE = 32


@dataclass(frozen=True)
class Budget:
    """``folds``: where the models are trained (constant velocity is scored on all five); the paper
    model trains ``steps`` x ``batch_size``, then its learned sampler ``sampler_steps`` (of the
    sampler's default batch), the slower per-frame baselines ``baseline_steps`` x ``baseline_batch``;
    every trained model is validated ``evaluations`` times, evenly over its steps."""

    name: str
    folds: tuple[str, ...]
    steps: int
    batch_size: int
    baseline_steps: int
    baseline_batch: int
    sampler_steps: int
    evaluations: int
    lr: float = 1e-3

    def __post_init__(self):
        # The trainer also validates at the last step: steps that the evaluations do not divide
        # would validate once more than meant, each pass a few seconds of a per-frame baseline.
        for name in ("steps", "baseline_steps"):
            if getattr(self, name) % self.evaluations:
                raise ValueError(
                    f"Budget {self.name!r}: {name}={getattr(self, name)} is not a multiple of "
                    f"evaluations={self.evaluations}"
                )


# The quick mode's 15 minutes from nothing hold the learned sampler's steps when its baselines train
# 200 steps (300 before the sampler) and every model is validated twice (docs/results.md).
QUICK = Budget(
    "quick mode: models trained on folds eth, hotel, zara1; 800 steps + learned sampler 150, baselines 200",
    ("eth", "hotel", "zara1"),
    800,
    64,
    200,
    64,
    150,
    2,
)
FULL = Budget(
    "full mode: 5 folds; 3000 steps + learned sampler 1500, baselines 1000",
    ("eth", "hotel", "univ", "zara1", "zara2"),
    3000,
    64,
    1000,
    64,
    1500,
    4,
)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 folds, short training (QUICK)")
    parser.add_argument("--raw", type=Path, default=REPO.parent / "shared" / "data" / "ethucy")
    parser.add_argument("--data", type=Path, default=REPO / "data" / "ethucy", help="converted dataset")
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "bench_ethucy")
    parser.add_argument(
        "--seed", type=int, default=0, help="training seed of every model (another seed: another --out)"
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch-size", type=int, default=512, help="evaluation batch size")
    return parser.parse_args(argv)


def ensure_data(args, folds: tuple[str, ...]) -> float:
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


def fold_data(args, fold: str):
    """The fold's windows (normalised with its training split) and its data config dict."""
    import yaml

    from mmf_rl.datasets import DataConfig, WindowDataset

    config = yaml.safe_load((args.data / f"{fold}.yaml").read_text()) | {
        "cache_dir": str(args.data / "cache"),
        "image_size": [IMAGE_SIZE, IMAGE_SIZE],
    }
    return WindowDataset(DataConfig.from_dict(config)), config


def train_overrides(args, budget: Budget, fold: str, label: str, run_dir: Path) -> list[str]:
    paper = label == PAPER
    steps = budget.steps if paper else budget.baseline_steps
    return [
        *TRAINED[label],
        *AUGMENT,
        f"data={args.data / f'{fold}.yaml'}",
        f"data.cache_dir={args.data / 'cache'}",
        f"data.image_size=[{IMAGE_SIZE},{IMAGE_SIZE}]",
        f"run_dir={run_dir}",
        f"trainer.total_steps={steps}",
        f"trainer.batch_size={budget.batch_size if paper else budget.baseline_batch}",
        f"trainer.lr={budget.lr}",
        f"trainer.seed={args.seed}",
        *([f"sampler.steps={budget.sampler_steps}", *SAMPLER] if paper else []),
        f"trainer.eval_every={max(steps // budget.evaluations, 1)}",
        f"trainer.checkpoint_every={steps}",
        f"trainer.warmup_steps={min(100, steps // 10)}",
        # The ELBO's KL warm-up, the paper model's only: the baselines' NLL reads no loss setting.
        *([f"loss.kl_warmup_steps={min(200, steps // 5)}"] if paper else []),
        "trainer.keep_checkpoints=1",
        "trainer.progress_bar=false",
        "calibrate=false",
        "logger=csv",
        f"device={args.device}",
    ]


# Settings that differ between machines, not between recipes: where the fold's data config, its
# window cache and the run live, the device. The run's directory already names its fold. A trained
# run's recipe is its training overrides without these: what this file decides, recorded in
# scores.json rather than read back from the run's config.yaml, which holds every composed setting,
# so that any setting a newer mmf-rl adds would refuse every completed run. A default changed since a
# run trained is not in its recipe: ``changed_defaults`` compares the config.yaml for those.
MACHINE_SETTINGS = frozenset({"data", "data.cache_dir", "run_dir", "device"})
# The same places in a composed config (the fold's data config names its dataset's root).
MACHINE_CONFIG_KEYS = frozenset({"data.root", "data.cache_dir", "run_dir", "device", "num_workers"})


def recipe(args, budget: Budget, fold: str, label: str) -> list[str]:
    """What a row's numbers depend on besides the data, as ``key=value`` settings."""
    if label in CV_RECIPES:
        return CV_RECIPES[label]
    overrides = train_overrides(args, budget, fold, label, args.out / fold / slug(label))
    return [o for o in overrides if o.split("=", 1)[0] not in MACHINE_SETTINGS]


# Settings this file began to override after runs had recorded their recipes, with the value those
# runs trained with (the configuration's default then): a recipe without one of them had that value.
IMPLIED_BEFORE_OVERRIDDEN = {
    "trainer.seed": "0",
    "augment.rotation": "0",
    "model.learned_samples": "0",
    "sampler.steps": "0",
    "sampler.diversity_weight": "20.0",
    "sampler.diversity_scale": "10.0",
}
# Settings this file once passed to every trained model though some models' loss never read them (the
# baselines' NLL has no KL to warm up): a recipe recording one where this file no longer passes it
# trained the same.
RECORDED_UNREAD = frozenset({"loss.kl_warmup_steps"})


def recipe_differences(expected: list[str], found: list[str]) -> list[str]:
    """``key: expected X, found Y`` for every setting the two recipes disagree on."""
    want, have = (dict(setting.split("=", 1) for setting in r) for r in (expected, found))
    have = {key: value for key, value in IMPLIED_BEFORE_OVERRIDDEN.items() if key in want} | have
    have = {key: value for key, value in have.items() if key in want or key not in RECORDED_UNREAD}
    return [
        f"{key}: expected {want.get(key, 'absent')}, found {have.get(key, 'absent')}"
        for key in dict.fromkeys([*want, *have])
        if want.get(key) != have.get(key)
    ]


def stale_runs(args, budget: Budget, folds) -> list[str]:
    """The completed runs this invocation would reuse but whose recipe differs from its own (or is
    unknown), each with the settings that differ: reused, they would mix recipes in one table."""
    stale = []
    for fold in sorted(folds):
        for label in [*(TRAINED if fold in budget.folds else ()), CV, CV_NOISE]:
            done = completed(args, fold, label)
            if done is None:
                continue
            run_dir = args.out / fold / slug(label)
            if "recipe" not in done:
                unknown = "recipe unknown (its scores.json predates recorded recipes): it cannot be checked"
                stale.append(f"{run_dir}: {unknown}")
            elif differences := recipe_differences(recipe(args, budget, fold, label), done["recipe"]):
                stale.append(f"{run_dir}: " + "; ".join(differences))
            elif label in TRAINED and (changed := changed_defaults(args, budget, fold, label, run_dir)):
                stale.append(f"{run_dir}: {changed}")
    return stale


def changed_defaults(args, budget: Budget, fold: str, label: str, run_dir: Path) -> str:
    """The settings a trained run's config.yaml holds with another value than this build composes from
    the same recipe (defaults changed since it trained), described; empty: none. Composing needs the
    fold's data config: before the conversion wrote it, nothing is compared."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.trainers.train_command import RUN_CONFIG, describe_trained_differently, trained_differently

    if not (args.data / f"{fold}.yaml").is_file() or not (run_dir / RUN_CONFIG).is_file():
        return ""
    cfg = compose_config("train", train_overrides(args, budget, fold, label, run_dir))
    return describe_trained_differently(trained_differently(run_dir, cfg, MACHINE_CONFIG_KEYS))


def check_reused(args, budget: Budget, folds) -> None:
    """Refuse, before anything runs, to mix completed runs of another recipe into this table."""
    if stale := stale_runs(args, budget, folds):
        raise SystemExit(
            f"ethucy: {args.out} holds completed runs of another recipe than this invocation's "
            f"({budget.name}):\n  " + "\n  ".join(stale) + "\nuse another --out, or delete a listed "
            "directory to compute it again with this recipe (nothing was deleted)"
        )


def val_curve(run_dir: Path) -> list[tuple[int, float]]:
    """``(step, val ADE in metres)`` the trainer logged at each of the budget's evaluations: the only
    evidence the budget is read from (the test scene is never looked at for it)."""
    path = run_dir / "logs" / "scalars" / "val" / "ade.csv"
    if not path.is_file():
        return []
    return [(int(float(s)), float(v)) for s, v in (row.split(",")[:2] for row in path.read_text().split())]


def score(model, data, split: str, args, deterministic: bool = False) -> dict:
    from mmf_rl.eval.trajectories import score_modes

    torch.manual_seed(0)  # the samples are repeatable
    loader = data.loader(split, args.batch_size)
    denormalize = data.normalizer.denormalize_target
    return score_modes(
        model.to(args.device).eval(), loader, denormalize, args.device, deterministic=deterministic
    )


def prior_scores(model, data, args) -> dict:
    """The paper model's scores with 20 draws from its prior instead of its learned sampler's codes."""
    with model.drawing_from_the_prior():
        return score(model, data, "test", args)


def run_trained(args, budget: Budget, fold: str, label: str, data) -> dict:
    """Train one model on the fold, score it on the test scene; ``scores.json`` written last."""
    import shutil

    from mmf_rl.configuration import compose_config
    from mmf_rl.eval.report import write_json
    from mmf_rl.models import load_trained_model
    from mmf_rl.trainers.train_command import train

    run_dir = args.out / fold / slug(label)
    if run_dir.exists():  # an interrupted run: start it again
        shutil.rmtree(run_dir)
    start = time.perf_counter()
    train(compose_config("train", train_overrides(args, budget, fold, label, run_dir)))
    trained = time.perf_counter() - start
    model, _, _ = load_trained_model(run_dir / "checkpoints", map_location=args.device)
    result = {
        "scores": score(model, data, "test", args, deterministic=label != PAPER),
        **({"prior_scores": prior_scores(model, data, args)} if label == PAPER else {}),
        "recipe": recipe(args, budget, fold, label),
        "train_seconds": trained,
        "val_ade": val_curve(run_dir),
    }
    result["seconds"] = time.perf_counter() - start
    write_json(run_dir / "scores.json", result)
    logger.info(
        "%s %s: trained in %.0f s, scored in %.0f s", fold, label, trained, result["seconds"] - trained
    )
    return result


def constant_velocity(data, heading_noise: float):
    from mmf_rl.models import build_model

    std = data.normalizer.stats["target/std"].tolist()
    return build_model(
        {"name": "constant_velocity", "heading_noise": heading_noise, "target_scale": std},
        data.specs,
        data.config.history,
        data.config.horizon,
        len(std),
    ).eval()


def run_constant_velocity(args, fold: str, data) -> dict[str, dict]:
    """Both constant-velocity rows; the sampler's angle std is the val split's best minADE20."""
    from mmf_rl.eval.report import write_json

    results = {}
    run_dir = args.out / fold / slug(CV)
    start = time.perf_counter()
    results[CV] = {
        "scores": score(constant_velocity(data, 0.0), data, "test", args, deterministic=True),
        "recipe": CV_RECIPES[CV],
    }
    results[CV]["seconds"] = time.perf_counter() - start
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(run_dir / "scores.json", results[CV])
    start = time.perf_counter()
    on_val = {
        sigma: score(constant_velocity(data, sigma), data, "val", args)["all"]["min_ade_k"]
        for sigma in HEADING_NOISE_GRID
    }
    sigma = min(on_val, key=on_val.get)
    results[CV_NOISE] = {
        "scores": score(constant_velocity(data, sigma), data, "test", args),
        "heading_noise": sigma,
        "recipe": CV_RECIPES[CV_NOISE],
        "val_min_ade_k": on_val,
        "seconds": time.perf_counter() - start,
    }
    (args.out / fold / slug(CV_NOISE)).mkdir(parents=True, exist_ok=True)
    write_json(args.out / fold / slug(CV_NOISE) / "scores.json", results[CV_NOISE])
    return results


def slug(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label.lower()).strip("_")


def completed(args, fold: str, label: str) -> dict | None:
    path = args.out / fold / slug(label) / "scores.json"
    return json.loads(path.read_text()) if path.is_file() else None


def draw_fold(args, fold: str, data) -> Path:
    """The paper model's 20 samples, the ground truth and the observed past of a few test agents,
    on the test scene's reference frame through its world->pixel map."""
    from mmf_rl import keys
    from mmf_rl.datasets import ethucy
    from mmf_rl.eval.trajectories import plot_forecasts_on_image, world_examples
    from mmf_rl.models import load_trained_model

    model, _, _ = load_trained_model(args.out / fold / slug(PAPER) / "checkpoints", map_location="cpu")
    ids = data.split_windows["test"]
    picks = ids[torch.linspace(0, len(ids) - 1, FIGURE_WINDOWS).long()]
    batch = data.batch(picks)
    torch.manual_seed(0)
    samples = model.eval().sample(batch.exclude(keys.TARGET), NUM_SAMPLES).get(keys.FORECAST_SAMPLES)
    stats = data.normalizer.stats

    def positions(b):
        return (
            b.get(("obs", "trajectory"))[..., :2] * stats["trajectory/std"][:2] + stats["trajectory/mean"][:2]
        )

    examples = world_examples(batch, samples.detach(), positions, data.normalizer.denormalize_target)
    scene = ethucy.load_scene(args.raw, ethucy.SCENE_OF[ethucy.FOLDS[fold][0]])
    title = (
        f"{fold}: paper model, {NUM_SAMPLES} learned samples (orange), ground truth (green), "
        "observed 8 steps (white)"
    )
    return plot_forecasts_on_image(
        scene.image, scene.to_pixel, examples, args.out / fold / "forecasts.png", title
    )


def run_fold(args, budget: Budget, fold: str) -> dict[str, dict]:
    """Every model's scores on the fold: the trained ones only in ``budget.folds``."""
    data, _ = fold_data(args, fold)
    results = {}
    for label in TRAINED if fold in budget.folds else ():
        results[label] = completed(args, fold, label) or run_trained(args, budget, fold, label, data)
    if PAPER in results:
        results[PAPER_PRIOR] = {"scores": results[PAPER]["prior_scores"]}
    if completed(args, fold, CV) and completed(args, fold, CV_NOISE):
        results |= {label: completed(args, fold, label) for label in (CV, CV_NOISE)}
    else:
        results |= run_constant_velocity(args, fold, data)
    if fold in budget.folds and not (args.out / fold / "forecasts.png").is_file():
        draw_fold(args, fold, data)
    return results


def average_section(title: str, average: dict) -> list[str]:
    from mmf_rl.eval.trajectories import relative_rise, scores_table

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


def markdown(per_fold: dict, averages: dict[str, dict], budget: Budget, seconds: dict) -> str:
    from mmf_rl.eval.trajectories import published_table, scores_table

    parts = [f"# ETH/UCY ({budget.name})\n"]
    for title, average in averages.items():
        parts += average_section(title, average)
    for fold, rows in per_fold.items():
        scores = {label: r["scores"] for label, r in rows.items()}
        windows = int(scores[CV]["all"]["windows"])
        sigma = rows[CV_NOISE]["heading_noise"]
        parts += [f"## {fold} ({windows} test windows; heading noise std {sigma} rad, chosen on val)\n"]
        parts += [scores_table(scores, DETERMINISTIC), ""]
        parts += [f"![forecasts]({fold}/forecasts.png)\n"] if fold in budget.folds else []
    parts += ["## Published (minADE20 / minFDE20, average of the 5 scenes)\n", published_table(), ""]
    parts += [f"Wall time in s (upper bounds: a shared, loaded machine): {json.dumps(seconds)}\n"]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    from mmf_rl.datasets import ethucy
    from mmf_rl.eval.report import write_json, write_text
    from mmf_rl.eval.trajectories import average_over_scenes, summary_line

    args = parse_args(argv)
    budget = QUICK if args.quick else FULL
    check_reused(args, budget, ethucy.FOLDS)
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    seconds = {"convert": ensure_data(args, tuple(ethucy.FOLDS))}
    per_fold = {}
    for fold in sorted(ethucy.FOLDS):
        fold_start = time.perf_counter()
        per_fold[fold] = run_fold(args, budget, fold)
        seconds[fold] = round(time.perf_counter() - fold_start)
    seconds["total"] = round(time.perf_counter() - start)
    scores = {f: {m: r["scores"] for m, r in rows.items()} for f, rows in per_fold.items()}
    average = average_over_scenes(scores, budget.folds)
    averages = {f"Average over the trained folds ({', '.join(budget.folds)})": average}
    if set(budget.folds) != set(per_fold):
        averages["Constant velocity, average over the 5 scenes (the protocol check)"] = average_over_scenes(
            scores
        )
    summary = summary_line(average, PAPER, CV, ["LF-LSTM", "MulT", CV, CV_NOISE], budget.name)
    results = {"mode": budget.name, "folds": per_fold, "averages": averages, "seconds": seconds}
    write_json(args.out / "results.json", results)
    write_text(args.out / "results.md", markdown(per_fold, averages, budget, seconds) + f"\n{summary}\n")
    print(summary)
    return 0


if __name__ == "__main__":
    from mmf_rl.cli import configure_logging

    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    raise SystemExit(main())
