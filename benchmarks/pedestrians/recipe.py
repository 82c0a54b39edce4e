"""What each row of ``benchmarks/ethucy.py`` is made with, and the check that a completed run was made
with this invocation's recipe.

A row's recipe is what its numbers depend on besides the data: a trained model's training overrides
(the mode's budget, the model, the augmentation, the seed) and its protocol (``sealed``: every option
in `OPTIONS` it reads chosen by the selection stage, with the candidates and the choice; ``probe``:
some given by hand), a constant-velocity row's heading-noise grid and where its std was picked, and
for every row the window set it is scored on. Each run records its recipe in its ``scores.json``, the
selection stage's inner runs too; before anything runs, the benchmark refuses to reuse a completed run
whose recipe differs, or that records none.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from benchmarks.pedestrians.selection import candidate_name, grid, held_out_pairs, is_pair

NUM_SAMPLES = 20  # the K of minADE20 / minFDE20
PAPER, CV, CV_NOISE = "paper model", "constant velocity", "constant velocity + heading noise"
PAPER_PRIOR = "paper model, prior samples"  # the paper model's weights, 20 draws from p(z | X)
TRAINED = {  # label -> model overrides
    PAPER: ("model=forecaster", "model.prior=learned", f"model.learned_samples={NUM_SAMPLES}"),
    "LF-LSTM": ("model=lf_lstm",),
    "MulT": ("model=mult",),
}


@dataclass(frozen=True)
class Option:
    """A recipe choice the sealed protocol can make per fold on held-out training scenes (``--select``):
    the models that read it, its value when given by hand, ``spell`` (a value in its one spelling, or
    ValueError) and ``overrides`` (a value's training overrides)."""

    models: tuple[str, ...]
    default: str
    spell: Callable[[str], str]
    overrides: Callable[[str], tuple[str, ...]]


def augment_group(value: str) -> str:
    """An ``augment`` config group: none, lerobot (its image transforms) or crop (those and a crop)."""
    if value not in ("none", "lerobot", "crop"):
        raise ValueError(f"expected none, lerobot or crop, found {value!r}")
    return value


def rotation_degrees(value: str) -> str:
    """``augment.rotation``: the largest angle a training window is turned by, 0 to 180 degrees."""
    degrees = float(value)
    if not 0 <= degrees <= 180:
        raise ValueError(f"expected 0 to 180 degrees, found {value!r}")
    return f"{degrees:g}"


def sampler_weights(value: str) -> str:
    """The learned sampler's diversity ``WEIGHT/SCALE`` (``5/5``)."""
    parts = value.split("/")
    if len(parts) != 2 or float(parts[0]) < 0 or float(parts[1]) <= 0:
        raise ValueError(f"expected WEIGHT/SCALE (weight >= 0, scale > 0), found {value!r}")
    return "/".join(f"{float(part):g}" for part in parts)


def sampler_overrides(value: str) -> tuple[str, ...]:
    weight, scale = (float(part) for part in value.split("/"))
    return (f"sampler.diversity_weight={weight}", f"sampler.diversity_scale={scale}")


# The options whose value was chosen while the test scenes were printed (docs/benchmarks/ethucy.md, "How
# the recipe was chosen"); each value given by hand is that value. A row reading one given by hand is a
# probe; one whose every option the selection stage chose is sealed.
# - augment: every trained model sees its scene crops through lerobot's default image transforms:
#   trained on four fixed reference frames, a model can learn their look (light, colour, sharpness),
#   which the held-out scene's frame does not share.
# - augment.rotation: each training window is turned by a random angle (trajectories, neighbours,
#   target and the north-up crop together), as Trajectron++ trains on these files: otherwise a model
#   learns the training scenes' walking directions, which the held-out scene need not share.
# - sampler: the learned sampler's diversity, AgentFormer's setting for hotel, zara1 and zara2, chosen
#   over its univ and eth settings on the folds' val files (the training scenes', not a held-out one),
#   with the test scenes' numbers printed beside. Named, so that a run trained with other weights is
#   never reused.
OPTIONS = {
    "augment": Option(tuple(TRAINED), "lerobot", augment_group, lambda value: (f"augment={value}",)),
    "augment.rotation": Option(
        tuple(TRAINED), "180", rotation_degrees, lambda value: (f"augment.rotation={value}",)
    ),
    "sampler": Option((PAPER,), "5/5", sampler_weights, sampler_overrides),
}
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


def parse_select(specs: list[str]) -> dict[str, list[str]]:
    """``--select NAME=V1,V2`` (repeated) -> ``{name: [values]}`` in the order given, each value spelled
    one way; ValueError naming what is wrong."""
    select: dict[str, list[str]] = {}
    for spec in specs:
        name, _, values = spec.partition("=")
        if name not in OPTIONS:
            raise ValueError(f"--select {spec}: unknown option {name!r}; expected one of {list(OPTIONS)}")
        if name in select:
            raise ValueError(f"--select {name} given twice: give its values once, comma separated")
        try:
            spelled = list(dict.fromkeys(OPTIONS[name].spell(value) for value in values.split(",")))
        except ValueError as error:
            raise ValueError(f"--select {spec}: {error}") from None
        if len(spelled) < 2:
            # One value is no choice: it would be an option given by hand, labelled as chosen.
            raise ValueError(f"--select {spec}: a choice needs two values or more")
        select[name] = spelled
    return select


def options_read(label: str) -> list[str]:
    """The options of `OPTIONS` that ``label``'s training reads, in their order."""
    return [name for name, option in OPTIONS.items() if label in option.models]


def option_values(label: str, chosen: dict[str, str] | None = None) -> dict[str, str]:
    """The value of every option ``label`` reads: ``chosen``'s, else the one given by hand."""
    return {name: (chosen or {}).get(name, OPTIONS[name].default) for name in options_read(label)}


def candidates(select: dict[str, list[str]], label: str) -> list[dict[str, str]]:
    """The selection's candidates for ``label``: the joint grid of the selected options it reads
    (none: it is not selected, no candidate)."""
    read = {name: values for name, values in select.items() if label in OPTIONS[name].models}
    return grid(read) if read else []


def protocol(args: argparse.Namespace, label: str) -> str:
    """``sealed``: the selection stage chose every option ``label`` reads; ``probe``: some are given by
    hand (their values were chosen while the test scenes were printed)."""
    return "sealed" if set(options_read(label)) <= set(args.select) else "probe"


def given_by_hand(args: argparse.Namespace, labels: Iterable[str]) -> list[str]:
    """``name=value`` of each option some of ``labels`` read that the invocation does not select."""
    read = {name for label in labels for name in options_read(label)}
    return [f"{name}={OPTIONS[name].default}" for name in OPTIONS if name in read and name not in args.select]


def data_config_path(args: argparse.Namespace, fold: str) -> Path:
    """An outer fold's data config (``--data/<fold>.yaml``, the conversion's) or a held-out pair's
    (``--data/held_out/<a>+<b>.yaml``, the selection stage's)."""
    return args.data / "held_out" / f"{fold}.yaml" if is_pair(fold) else args.data / f"{fold}.yaml"


def run_path(args: argparse.Namespace, fold: str, label: str, chosen: dict[str, str] | None = None) -> Path:
    """A row's run, ``<out>/<fold>/<model>``, or an inner run, ``<out>/select/<pair>/<model>/<values>``
    named by the value of every option it reads: one run for every candidate training the same."""
    if not is_pair(fold):
        return args.out / fold / slug(label)
    return args.out / "select" / fold / slug(label) / slug(candidate_name(option_values(label, chosen)))


def train_overrides(
    args: argparse.Namespace,
    budget: Budget,
    fold: str,
    label: str,
    run_dir: Path,
    chosen: dict[str, str] | None = None,
) -> list[str]:
    """The ``mmf-rl train`` overrides that train ``label`` on ``fold`` (or a held-out pair) into
    ``run_dir``, its options ``chosen``'s or given by hand."""
    paper = label == PAPER
    steps = budget.steps if paper else budget.baseline_steps
    values = option_values(label, chosen)

    def option(name: str) -> tuple[str, ...]:
        return OPTIONS[name].overrides(values[name]) if name in values else ()

    return [
        *TRAINED[label],
        *option("augment"),
        *option("augment.rotation"),
        f"data={data_config_path(args, fold)}",
        f"data.cache_dir={args.data / 'cache'}",
        f"data.image_size=[{IMAGE_SIZE},{IMAGE_SIZE}]",
        f"run_dir={run_dir}",
        f"trainer.total_steps={steps}",
        f"trainer.batch_size={budget.batch_size if paper else budget.baseline_batch}",
        f"trainer.lr={budget.lr}",
        f"trainer.seed={args.seed}",
        *([f"sampler.steps={budget.sampler_steps}", *option("sampler")] if paper else []),
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


def recipe(
    args: argparse.Namespace, budget: Budget, fold: str, label: str, chosen: dict[str, str] | None = None
) -> list[str]:
    """What a row's numbers depend on besides the data, as ``key=value`` settings: how its model is made
    (its options ``chosen``'s or given by hand), by which protocol, and the windows it is scored on. An
    inner run (``fold`` a held-out pair) has no protocol: it is the selection's evidence."""
    if label in CV_RECIPES:
        return constant_velocity_recipe(args, label)
    overrides = train_overrides(args, budget, fold, label, run_path(args, fold, label, chosen), chosen)
    settings = [o for o in overrides if o.split("=", 1)[0] not in MACHINE_SETTINGS]
    return [*settings, *([] if is_pair(fold) else protocol_settings(args, label, chosen)), scored_on(args)]


def protocol_settings(args: argparse.Namespace, label: str, chosen: dict[str, str] | None) -> list[str]:
    """A row's protocol, the candidates of each option the selection chose for it, and its choice."""
    selected = [name for name in options_read(label) if name in args.select]
    return [
        f"protocol={protocol(args, label)}",
        *(f"candidates.{name}={','.join(args.select[name])}" for name in selected),
        *(f"chosen.{name}={chosen[name]}" for name in selected if chosen and name in chosen),
    ]


def recorded_choice(args: argparse.Namespace, found: list[str]) -> dict[str, str]:
    """The choice a completed row records for the options this invocation selects: its recipe is
    checked with it before the selection runs, the choice itself once the selection has run."""
    settings = dict(setting.split("=", 1) for setting in found)
    return {name: settings[f"chosen.{name}"] for name in args.select if f"chosen.{name}" in settings}


def constant_velocity_recipe(args: argparse.Namespace, label: str) -> list[str]:
    """A constant-velocity row's recipe (``label`` a key of ``CV_RECIPES``): no training, its heading
    noise (the sealed protocol picks its std on the held-out training scenes, a probe on the fold's
    val split) and the windows it is scored on."""
    picked = [f"heading_noise_chosen_on={'held_out_scenes' if args.select else 'val'}"]
    return [*CV_RECIPES[label], *(picked if label == CV_NOISE else []), scored_on(args)]


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
    "protocol": "probe",
    "heading_noise_chosen_on": "val",
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


def completed(
    args: argparse.Namespace, fold: str, label: str, chosen: dict[str, str] | None = None
) -> dict | None:
    """A run's ``scores.json`` (a row's on ``fold``, or an inner run's on a held-out pair): None until
    its run completes (written last)."""
    path = run_path(args, fold, label, chosen) / "scores.json"
    return json.loads(path.read_text()) if path.is_file() else None


def inner_runs(args: argparse.Namespace, budget: Budget) -> list[tuple[str, str, dict[str, str]]]:
    """``(pair, model, candidate)`` of every inner run the selection stage reads: each trained model's
    candidates on each pair holding out a fold it trains on (none without ``--select``)."""
    from mmf_rl.datasets.ethucy import FOLDS

    return [
        (pair, label, candidate)
        for pair in held_out_pairs(FOLDS, budget.folds)
        for label in TRAINED
        for candidate in candidates(args.select, label)
    ]


def stale_runs(args: argparse.Namespace, budget: Budget, folds: Iterable[str]) -> list[str]:
    """The completed runs this invocation would reuse but whose recipe differs from its own (or is
    unknown), each with the settings that differ: reused, they would mix recipes in one table."""
    rows = [
        (fold, label, None)
        for fold in sorted(folds)
        for label in [*(TRAINED if fold in budget.folds else ()), CV, CV_NOISE]
    ]
    checked = (stale_run(args, budget, *run) for run in [*rows, *inner_runs(args, budget)])
    return [line for line in checked if line]


def stale_run(
    args: argparse.Namespace, budget: Budget, fold: str, label: str, chosen: dict[str, str] | None
) -> str:
    """Why a completed run is not this invocation's (``run: differences``); empty: it is, or it has not
    completed. A row the selection chose for is checked with the choice it records (`recorded_choice`)."""
    done = completed(args, fold, label, chosen)
    path = run_path(args, fold, label, chosen)
    if done is None:
        return ""
    if "recipe" not in done:
        return f"{path}: recipe unknown (its scores.json predates recorded recipes): it cannot be checked"
    if not is_pair(fold) and label in TRAINED:
        chosen = recorded_choice(args, done["recipe"])
    if differences := recipe_differences(recipe(args, budget, fold, label, chosen), done["recipe"]):
        return f"{path}: " + "; ".join(differences)
    if label in TRAINED and (changed := changed_defaults(args, budget, fold, label, path, chosen)):
        return f"{path}: {changed}"
    return ""


def changed_defaults(
    args: argparse.Namespace,
    budget: Budget,
    fold: str,
    label: str,
    run_dir: Path,
    chosen: dict[str, str] | None = None,
) -> str:
    """The settings a trained run's config.yaml holds with another value than this build composes from
    the same recipe (defaults changed since it trained), described; empty: none. Composing needs the
    fold's data config: before the conversion (or the selection stage) wrote it, nothing is compared."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.trainers.training import RUN_CONFIG, describe_trained_differently, trained_differently

    if not data_config_path(args, fold).is_file() or not (run_dir / RUN_CONFIG).is_file():
        return ""
    cfg = compose_config("train", train_overrides(args, budget, fold, label, run_dir, chosen))
    return describe_trained_differently(trained_differently(run_dir, cfg, MACHINE_CONFIG_KEYS))


def check_reused(args: argparse.Namespace, budget: Budget, folds: Iterable[str]) -> None:
    """Refuse, before anything runs, to mix completed runs of another recipe into this table."""
    if stale := stale_runs(args, budget, folds):
        raise SystemExit(
            f"ethucy: {args.out} holds completed runs of another recipe than this invocation's "
            f"({budget.name}):\n  " + "\n  ".join(stale) + "\nuse another --out, or delete a listed "
            "directory to compute it again with this recipe (nothing was deleted)"
        )
