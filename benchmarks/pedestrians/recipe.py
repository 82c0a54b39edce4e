"""What each row of ``benchmarks/ethucy.py`` is made with, and the check that a completed run was made
with this invocation's recipe.

A row's recipe is what its numbers depend on besides the data: a trained model's training overrides
(the mode's budget, the model, the augmentation, the seed), a constant-velocity row's heading-noise
grid, and for every row the window set it is scored on. Each run records its recipe in its
``scores.json``; before anything runs, the benchmark refuses to reuse a completed run whose recipe
differs, or that records none.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

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
# The learned sampler's diversity: AgentFormer's setting for hotel, zara1 and zara2, chosen over its
# univ and eth settings on the folds' validation scenes (docs/results.md).
# Named here so that a run trained with other weights is never reused.
SAMPLER = ("sampler.diversity_weight=5.0", "sampler.diversity_scale=5.0")
HEADING_NOISE_GRID = (0.05, 0.1, 0.15, 0.2, 0.3, 0.45)  # radians, the sampler's std picked on val
# The constant-velocity rows' recipes (see ``recipe``): they are computed together, from no training.
CV_RECIPES = {CV: ["heading_noise=0.0"], CV_NOISE: [f"heading_noise_grid={list(HEADING_NOISE_GRID)}"]}


# Scene crops are resized to this side in the window cache: the baselines run their ConvNet on every
# frame (the paper model stacks the 8 frames), which at the converter's 64 px made their training
# and scoring most of the benchmark's time (docs/results.md).
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


# The quick mode's time budget holds the learned sampler's steps when its baselines train 200 steps
# and every model is validated twice (docs/results.md).
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


def train_overrides(
    args: argparse.Namespace, budget: Budget, fold: str, label: str, run_dir: Path
) -> list[str]:
    """The ``mmf-rl train`` overrides that train ``label`` on ``fold`` into ``run_dir``."""
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
# run's recipe is its training overrides without these: what the benchmark decides, recorded in
# scores.json rather than read back from the run's config.yaml, which holds every composed setting,
# so that any setting a newer mmf-rl adds would refuse every completed run. A default changed since a
# run trained is not in its recipe: ``changed_defaults`` compares the config.yaml for those.
MACHINE_SETTINGS = frozenset({"data", "data.cache_dir", "run_dir", "device"})
# The same places in a composed config (the fold's data config names its dataset's root).
MACHINE_CONFIG_KEYS = frozenset({"data.root", "data.cache_dir", "run_dir", "device", "num_workers"})


def recipe(args: argparse.Namespace, budget: Budget, fold: str, label: str) -> list[str]:
    """What a row's numbers depend on besides the data, as ``key=value`` settings: how its model is made
    and the windows it is scored on."""
    if label in CV_RECIPES:
        return constant_velocity_recipe(args, label)
    overrides = train_overrides(args, budget, fold, label, args.out / fold / slug(label))
    return [*(o for o in overrides if o.split("=", 1)[0] not in MACHINE_SETTINGS), scored_on(args)]


def constant_velocity_recipe(args: argparse.Namespace, label: str) -> list[str]:
    """A constant-velocity row's recipe (``label`` a key of ``CV_RECIPES``): no training, its heading
    noise and the windows it is scored on."""
    return [*CV_RECIPES[label], scored_on(args)]


def scored_on(args: argparse.Namespace) -> str:
    """The recipe's setting naming the window set every row is scored on (the models train on every
    window of the training split whatever it is)."""
    return f"window_set={args.window_set}"


# Settings the benchmark began to override or record after runs had recorded their recipes, with the
# value those runs had (the configuration's default then): a recipe without one of them had that value.
IMPLIED_BEFORE_OVERRIDDEN = {
    "window_set": "trajectron",
    "trainer.seed": "0",
    "augment.rotation": "0",
    "model.learned_samples": "0",
    "sampler.steps": "0",
    "sampler.diversity_weight": "20.0",
    "sampler.diversity_scale": "10.0",
}
# Settings the benchmark once passed to every trained model though some models' loss never read them
# (the baselines' NLL has no KL to warm up): a recipe recording one where the benchmark no longer passes
# it trained the same.
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


def slug(label: str) -> str:
    """A row's directory name under its fold's."""
    return "".join(c if c.isalnum() else "_" for c in label.lower()).strip("_")


def completed(args: argparse.Namespace, fold: str, label: str) -> dict | None:
    """A row's ``scores.json`` on ``fold``: None until its run completes (written last)."""
    path = args.out / fold / slug(label) / "scores.json"
    return json.loads(path.read_text()) if path.is_file() else None


def stale_runs(args: argparse.Namespace, budget: Budget, folds: Iterable[str]) -> list[str]:
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


def changed_defaults(args: argparse.Namespace, budget: Budget, fold: str, label: str, run_dir: Path) -> str:
    """The settings a trained run's config.yaml holds with another value than this build composes from
    the same recipe (defaults changed since it trained), described; empty: none. Composing needs the
    fold's data config: before the conversion wrote it, nothing is compared."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.trainers.training import RUN_CONFIG, describe_trained_differently, trained_differently

    if not (args.data / f"{fold}.yaml").is_file() or not (run_dir / RUN_CONFIG).is_file():
        return ""
    cfg = compose_config("train", train_overrides(args, budget, fold, label, run_dir))
    return describe_trained_differently(trained_differently(run_dir, cfg, MACHINE_CONFIG_KEYS))


def check_reused(args: argparse.Namespace, budget: Budget, folds: Iterable[str]) -> None:
    """Refuse, before anything runs, to mix completed runs of another recipe into this table."""
    if stale := stale_runs(args, budget, folds):
        raise SystemExit(
            f"ethucy: {args.out} holds completed runs of another recipe than this invocation's "
            f"({budget.name}):\n  " + "\n  ".join(stale) + "\nuse another --out, or delete a listed "
            "directory to compute it again with this recipe (nothing was deleted)"
        )
