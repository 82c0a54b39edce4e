"""Missing-modality accuracy benchmark on the recorded push dataset (paper Tables 3, 4, 5).

    .venv/bin/python benchmarks/accuracy.py --standard     # every entry, 3 seeds (see STANDARD below)
    .venv/bin/python benchmarks/accuracy.py --standard --jobs 2   # two runs at once, one thread each
    .venv/bin/python benchmarks/accuracy.py --quick        # paper model, zero-fill baselines, w/o L_mis
    .venv/bin/python benchmarks/accuracy.py --tiny         # smoke run of the code paths (meaningless numbers)
    .venv/bin/python benchmarks/accuracy.py                # the full budget (see FULL below)

Every entry is trained with the same step budget, batch size and seeds on the same recording
(fixed train/val/test episodes: ``data.split_seed``) with ``mmf-rl train``'s ``train(cfg)``, then
scored on every presence subset of the test split with ``mmf-rl eval``'s ``run_evaluation(cfg)``;
the benchmark also runs each trained model over the test windows itself to keep every window's
squared error with its episode (``<run>/eval/window_errors.json``). The metric is MSE on the
normalised target (MultiBench's push metric).

Each cell is the mean over seeds, with a 95% interval from a paired bootstrap over test episodes:
one seeded generator draws the episode resamples once, and every entry, seed and subset is
re-scored on the same resamples. "Best or tied" means the intervals overlap the best's.

Entries (``ENTRIES``; a new model option is one line there):

* ``paper``: the attention CVAE with the configuration defaults (ELBO + ``L_mis``); ``variant``
  rows: the same model with one of issue #13's options (learned prior, drop distribution, GSNN).
* Baselines, two protocols for absent modalities at test time:
  - ``zero-fill``: trained once on all modalities; ``LF-LSTM`` and ``MulT`` see an absent
    modality as zeros, ``MVAE`` drops its expert from the product (its native handling);
  - ``retrained``: the paper's protocol, one model per subset trained with only that subset's
    modalities present (``+data.missing.<m>=1.0`` for the others); its ``all`` cell is the model
    trained on all modalities.
* Ablations of the paper's model: the multimodal encoder replaced by ``linear``, ``average``,
  ``sum``, ``cross_attention`` fusion (Table 4); without ``L_mis`` (``loss=no_mis``) and trained
  with 50 % of the image samples missing (Table 5); and, to separate the image encoder from the
  fusion, the paper model with the baselines' per-frame image encoder (``conv_gru``). The four fusion
  ablations again under the learned prior (``learned fusion``), compared with the learned prior's own
  attention run: only there does the fusion act at test time.

The dataset is recorded if ``--data`` does not exist (the mode's episode count x 50 steps at
64x64, 2 workers). Completed runs (``<out>/<entry>/seed<k>/eval/window_errors.json``) are reused,
so an interrupted benchmark resumes; delete ``--out`` to start over. Writes ``<out>/results.md``
and ``<out>/results.json`` and ends with one line:
``summary: paper model best or tied in X/Y subsets (zero-fill baselines), R/3 paper subsets vs
retrained; fusion spread S; mean degradation paper P%, best baseline Q%`` (``-`` where the run
lacks the entries a number needs).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ["force", "image", "proprio"]
# MuJoCo Push subsets reported in the paper (Table 3): image+force+proprio, image+force, image+proprio.
PAPER_SUBSETS = ("all", "without_proprio", "without_force")
# Issue #13: the forecast's 90% interval must cover 80-97% of the test futures in every subset.
COVERAGE_TARGET = (0.80, 0.97)
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
LEVEL = 0.95


@dataclass(frozen=True)
class Budget:
    image_size: int
    batch_size: int
    steps: int
    seeds: tuple[int, ...]
    entries: tuple[str, ...] | None  # None: every entry
    episodes: int  # recorded when --data does not exist
    retrained_subsets: str = "all"  # "all" | "paper": the subsets the retrained baselines are trained for


# Tiny: every code path (each entry kind, seeds averaged, the bootstrap) on a small recording in a few
# minutes; the numbers mean nothing.
TINY = Budget(
    image_size=32,
    batch_size=8,
    steps=4,
    seeds=(0, 1),
    episodes=16,
    retrained_subsets="paper",
    entries=("paper", "LF-LSTM", "LF-LSTM (retrained)", "paper fusion=linear", "paper w/o L_mis"),
)
# Quick: the paper model, the zero-fill baselines and the L_mis ablation.
QUICK = Budget(
    image_size=32,
    batch_size=32,
    steps=300,
    seeds=(0, 1, 2),
    episodes=200,
    entries=("paper", "paper w/o L_mis", "LF-LSTM", "MVAE", "MulT"),
)
# Standard: every entry, 3 seeds, at the budget of issue #13's single-change runs (1000 steps of batch 32,
# 32x32), for <= 75 min on 2 cores. The retrained baselines are trained for the paper's three subsets
# only (the ones the target compares them on): the paper model, 7 variants, 3 zero-fill
# baselines, 3 x 2 retrained, 4 + 4 fusion ablations (standard and learned prior) and 3 other ablations
# = 28 trainings a seed, 84 in all. results.md gives the wall time and projects this mode's time from
# the per-step times of the run that wrote it.
STANDARD = Budget(
    image_size=32,
    batch_size=32,
    steps=1000,
    seeds=(0, 1, 2),
    episodes=200,
    entries=None,
    retrained_subsets="paper",
)
# Full: every entry, the retrained baselines for every subset, 3 seeds, 2000 steps of batch 64 at 32x32
# (MultiBench's gentle_push image size). Meant for a GPU (--device auto) or a long night on 2 cores
# (~6 h from the same measurement).
FULL = Budget(image_size=32, batch_size=64, steps=2000, seeds=(0, 1, 2), episodes=200, entries=None)
MODES = {"tiny": TINY, "quick": QUICK, "standard": STANDARD, "full": FULL}


@dataclass(frozen=True)
class Entry:
    label: str
    kind: str  # paper | variant | zero-fill | retrained | fusion | learned fusion | ablation
    overrides: tuple[str, ...]
    # retrained: the zero-fill entry whose all-modality run gives its "all" cell; learned fusion: the
    # entry it is compared with (the same prior with the paper's fusion)
    base: str | None = None


LEARNED = ("model.prior=learned",)
# The sequence encoder issue #6's model used for force and proprioception (the default is now "mlp").
GRU_VECTORS = (
    "data.modalities.force={feature:observation.force,encoder:gru}",
    "data.modalities.proprio={feature:observation.state,encoder:gru}",
)
# One token per step for every modality (the image's per frame).
STEP_TOKENS = (
    "data.modalities.image.encoder=conv_frames",
    "data.modalities.force.encoder=steps",
    "data.modalities.proprio.encoder=steps",
)
ENTRIES = [
    Entry("paper", "paper", ("model=forecaster",)),
    # Issue #13's options of the paper model. The defaults (standard prior, MLP window encoders for the
    # vector modalities, L_mis dropping one modality) were chosen from this table; the learned prior's
    # options are measured on top of the learned prior. The GRU row is issue #6's model.
    Entry("paper prior=learned", "variant", ("model=forecaster", *LEARNED)),
    Entry(
        "paper prior=learned, GRU vector encoders", "variant", ("model=forecaster", *LEARNED, *GRU_VECTORS)
    ),
    Entry(
        "paper prior=learned, drop 1..M-1", "variant", ("model=forecaster", *LEARNED, "loss.max_dropped=null")
    ),
    Entry("paper prior=learned, GSNN 0.5", "variant", ("model=forecaster", *LEARNED, "loss.gsnn_weight=0.5")),
    Entry(
        "paper prior=learned, degraded NLL 1.0",
        "variant",
        ("model=forecaster", *LEARNED, "loss.dropped_nll_weight=1.0"),
    ),
    Entry("paper GRU vector encoders (issue #6)", "variant", ("model=forecaster", *GRU_VECTORS)),
    Entry("paper, drop 1..M-1", "variant", ("model=forecaster", "loss.max_dropped=null")),
    # The fusion on every test forecast: the decoder reads the multimodal encoder's mixed tokens, or
    # decodes at q(z|X)'s mean (eqs. 10 and 15); and tokens per step instead of one per modality.
    Entry("paper, decoder reads mixed tokens", "variant", ("model=forecaster", "model.decoder_input=mixed")),
    Entry("paper eval_latent=posterior", "variant", ("model=forecaster", "model.eval_latent=posterior")),
    Entry(
        "paper, mixed tokens, per-frame image tokens",
        "variant",
        ("model=forecaster", "model.decoder_input=mixed", "data.modalities.image.encoder=conv_frames"),
    ),
    Entry(
        "paper, mixed tokens, per-step tokens",
        "variant",
        ("model=forecaster", "model.decoder_input=mixed", *STEP_TOKENS),
    ),
    Entry("LF-LSTM", "zero-fill", ("model=lf_lstm",)),
    Entry("MVAE", "zero-fill", ("model=mvae",)),
    Entry("MulT", "zero-fill", ("model=mult",)),
    Entry("LF-LSTM (retrained)", "retrained", ("model=lf_lstm",), base="LF-LSTM"),
    Entry("MVAE (retrained)", "retrained", ("model=mvae",), base="MVAE"),
    Entry("MulT (retrained)", "retrained", ("model=mult",), base="MulT"),
    Entry("paper fusion=linear", "fusion", ("model=forecaster", "model.fusion=linear")),
    Entry("paper fusion=average", "fusion", ("model=forecaster", "model.fusion=average")),
    Entry("paper fusion=sum", "fusion", ("model=forecaster", "model.fusion=sum")),
    Entry("paper fusion=cross_attention", "fusion", ("model=forecaster", "model.fusion=cross_attention")),
    # Table 4 where the fusion acts at test time: under the standard prior a forecast is decoded at z = 0
    # and the fusion only shapes training (through q(z|X)); under the learned prior it gives p(z|X).
    *(
        Entry(
            f"paper prior=learned, fusion={fusion}",
            "learned fusion",
            ("model=forecaster", *LEARNED, f"model.fusion={fusion}"),
            base="paper prior=learned",
        )
        for fusion in ("linear", "average", "sum", "cross_attention")
    ),
    Entry("paper w/o L_mis", "ablation", ("model=forecaster", "loss=no_mis")),
    Entry("paper, L_mis teacher not detached", "ablation", ("model=forecaster", "loss.detach_teacher=false")),
    Entry(
        "paper, 50% image missing in training", "ablation", ("model=forecaster", "+data.missing.image=0.5")
    ),
    # Not in the paper: the image encoder MulT and LF-LSTM use (a ConvNet per frame, then a GRU)
    # instead of the default frame-stacked ConvNet, to tell the encoder from the fusion.
    Entry(
        "paper, per-frame image encoder",
        "ablation",
        ("model=forecaster", "data.modalities.image={feature:observation.images.front,encoder:conv_gru}"),
    ),
]
BASELINE_KINDS = ("zero-fill", "retrained")


# ---------------------------------------------------------------------------------------------
# Statistics: pure functions over per-window errors (tested in tests/test_benchmarks_accuracy.py).
# Hand-written: a paired bootstrap over groups (episodes) of ratio means, shared by many cells, is
# a few tensor lines; scipy.stats.bootstrap resamples each statistic independently (no pairing).
# ---------------------------------------------------------------------------------------------


@dataclass
class Cell:
    """One entry x subset: MSE averaged over seeds, its bootstrap interval and resampled values."""

    mean: float
    low: float
    high: float
    per_seed: list[float]
    windows: int
    samples: torch.Tensor = field(repr=False)  # [resamples] the statistic on each episode resample

    def to_dict(self) -> dict:
        return {
            "mean": self.mean,
            "low": self.low,
            "high": self.high,
            "per_seed": self.per_seed,
            "windows": self.windows,
        }


def episode_totals(
    episodes: Sequence[int], errors: Sequence[float], order: Sequence[int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-episode sum of ``errors`` and window count ``[E]``, episodes in ``order``."""
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
    subsets are compared on the same resampled test sets (a paired bootstrap)."""
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
    statistic is their mean over seeds (the interval is over test episodes, not over seeds)."""
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


def ordered_subsets(names: Sequence[str]) -> list[str]:
    """The paper's three MuJoCo Push subsets first, then the others in their given order."""
    return [s for s in PAPER_SUBSETS if s in names] + [s for s in names if s not in PAPER_SUBSETS]


@dataclass
class Table:
    subsets: list[str]  # headline order
    cells: dict[str, dict[str, Cell]] = field(default_factory=dict)  # label -> subset -> cell
    kinds: dict[str, str] = field(default_factory=dict)

    def labels(self, *kinds: str) -> list[str]:
        return [label for label, kind in self.kinds.items() if kind in kinds]

    def degradation(self, label: str, subset: str) -> float:
        """Relative MSE increase against the same entry with all modalities."""
        return self.cells[label][subset].mean / self.cells[label]["all"].mean - 1

    def mean_degradation(self, label: str) -> float:
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


def summarize(table: Table) -> tuple[str, dict]:
    won, compared = table.wins(("zero-fill",), table.subsets)
    retrained_won, retrained_compared = table.wins(("retrained",), PAPER_SUBSETS)
    spread = table.fusion_spread()
    # Mean degradations compare like with like: only baselines scored on every subset (in standard mode
    # the retrained ones cover the paper's three).
    baselines = [
        label for label in table.labels(*BASELINE_KINDS) if set(table.cells[label]) == set(table.subsets)
    ]
    paper_deg = table.mean_degradation("paper")
    best_baseline_deg = min((table.mean_degradation(label) for label in baselines), default=None)
    line = (
        f"summary: paper model best or tied in {won if compared else '-'}/{compared} subsets "
        "(zero-fill baselines), "
        f"{retrained_won if retrained_compared else '-'}/3 paper subsets vs retrained; "
        f"fusion spread {'-' if spread is None else f'{100 * spread:.0f}%'}; "
        f"mean degradation paper {100 * paper_deg:.0f}%, best baseline "
        f"{'-' if best_baseline_deg is None else f'{100 * best_baseline_deg:.0f}%'}"
    )
    return line, {
        "best_or_tied_vs_zero_fill": won,
        "subsets_vs_zero_fill": compared,
        "paper_subsets_best_or_tied_vs_retrained": retrained_won,
        "paper_subsets_vs_retrained": retrained_compared,
        "fusion_spread": spread,
        "paper_mean_degradation": paper_deg,
        "best_baseline_mean_degradation": best_baseline_deg,
    }


def reference_of(label: str, kind: str) -> str:
    """The entry a rival is compared with: ``paper``, or for a learned-prior fusion ablation the learned
    prior with the paper's fusion (its ``base``)."""
    if kind == "learned fusion":
        return next(e.base for e in ENTRIES if e.label == label)
    return "paper"


def paired_comparisons(table: Table) -> dict[str, dict[str, dict]]:
    """Per subset: ``reference - rival`` intervals (paired) of each baseline against the paper model and
    of each fusion ablation against the same model with the paper's fusion (``reference_of``)."""
    out: dict[str, dict[str, dict]] = {}
    for s in table.subsets:
        for label in table.labels(*BASELINE_KINDS, "fusion", "learned fusion"):
            reference = reference_of(label, table.kinds[label])
            ours = table.cells.get(reference, {}).get(s)
            if ours is not None and s in table.cells[label]:
                low, high = difference_interval(ours, table.cells[label][s])
                out.setdefault(s, {})[label] = {
                    "reference": reference,
                    "difference": ours.mean - table.cells[label][s].mean,
                    "low": low,
                    "high": high,
                }
    return out


# ---------------------------------------------------------------------------------------------
# Runs: train, evaluate, keep the per-window errors.
# ---------------------------------------------------------------------------------------------


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text).strip("_").lower()


def record_dataset(root: Path, episodes: int) -> float:
    """Record the benchmark's push dataset with ``mmf-rl record``; returns the wall time."""
    start = time.perf_counter()
    cmd = [
        sys.executable,
        "-m",
        "mmf_rl.cli",
        "record",
        "--out",
        str(root),
        "--episodes",
        str(episodes),
        "--workers",
        "2",
        "--image-size",
        "64",
        "--steps",
        "50",
        "--seed",
        "0",
    ]
    print("recording:", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    return time.perf_counter() - start


def subsets(modalities: Sequence[str] = MODALITIES) -> list[tuple[str, dict[str, bool]]]:
    from mmf_rl.datasets import presence_subsets

    return list(presence_subsets(list(modalities)))


def train_overrides(
    entry: Entry, seed: int, budget: Budget, args, run_dir: Path, extra: tuple[str, ...] = ()
) -> list[str]:
    return [
        *entry.overrides,
        *extra,
        f"data.root={args.data}",
        f"data.cache_dir={args.out / 'cache'}",
        f"data.image_size=[{budget.image_size},{budget.image_size}]",
        f"run_dir={run_dir}",
        f"trainer.total_steps={budget.steps}",
        f"trainer.batch_size={budget.batch_size}",
        f"trainer.seed={seed}",
        f"trainer.eval_every={budget.steps}",
        f"trainer.checkpoint_every={budget.steps}",
        f"trainer.warmup_steps={min(100, budget.steps // 10)}",
        f"loss.kl_warmup_steps={min(200, budget.steps // 5)}",
        "trainer.keep_checkpoints=1",
        "trainer.progress_bar=false",
        "logger=csv",
        "num_workers=2",
        f"device={args.device}",
    ]


def build_cache(budget: Budget, args) -> float:
    """Build (or open) the window cache once before the first training, so no run's time includes it;
    returns the wall time."""
    from mmf_rl.configuration import compose_config, to_container
    from mmf_rl.datasets import DataConfig, WindowDataset

    start = time.perf_counter()
    cfg = compose_config("train", train_overrides(ENTRIES[0], 0, budget, args, args.out / "cache"))
    WindowDataset(DataConfig.from_dict(to_container(cfg.data)), num_workers=2)
    return time.perf_counter() - start


def check_entries(entries: Sequence[Entry], budget: Budget, args) -> None:
    """Compose every entry's training config before the first training: an option this build lacks
    fails here in seconds, naming the entry, not after an hour of runs."""
    from mmf_rl.configuration import ConfigError, compose_config

    problems = []
    for entry in entries:
        try:
            compose_config("train", train_overrides(entry, 0, budget, args, args.out / "check"))
        except ConfigError as err:
            problems.append(f"{entry.label!r} ({' '.join(entry.overrides)}): {' '.join(str(err).split())}")
    if problems:
        raise SystemExit(
            "accuracy benchmark: these entries do not compose with this build's configs:\n  "
            + "\n  ".join(problems)
            + "\nleave them out with --entries, or add the option they set"
        )


@torch.no_grad()
def window_errors(run_dir: Path, device: str, batch_size: int = 256) -> dict[str, dict[str, list]]:
    """Every test window's squared error (mean over ``T x D``, normalised target) per presence subset,
    with its window id and episode: ``{subset: {"window", "episode", "squared_error"}}``.

    The windows and normalisation are those of ``run_evaluation`` (the test split in order, the
    checkpoint's statistics); ``run_one`` checks the means agree with its MSE."""
    from mmf_rl import keys
    from mmf_rl.datasets import DataConfig, WindowDataset, apply_presence_subset
    from mmf_rl.datasets.splits import Normalizer
    from mmf_rl.models import load_trained_model

    model, stats, data_config = load_trained_model(run_dir / "checkpoints", map_location=device)
    data = WindowDataset(DataConfig.from_dict(data_config))
    data.normalizer = Normalizer(stats)
    ids = data.split_windows["test"]
    out = {}
    for name, subset in subsets([s.name for s in data.specs]):  # the trained data's modalities
        rows: dict[str, list] = {"window": [], "episode": [], "squared_error": []}
        for chunk in ids.split(batch_size):
            batch = data.batch(chunk, "test")
            # apply_presence_subset keeps the windows that still have one of the subset's modalities.
            kept = torch.zeros(len(chunk), dtype=torch.bool)
            for m, keep in subset.items():
                kept |= batch.get(keys.present_key(m)) & keep
            batch = apply_presence_subset(batch, subset).to(device)
            if batch.shape[0] == 0:
                continue
            loc = model(batch.clone(False)).get(keys.FORECAST_LOC)
            rows["window"] += chunk[kept].tolist()
            rows["episode"] += data.window_episode[chunk[kept]].tolist()
            rows["squared_error"] += ((loc - batch.get(keys.TARGET)) ** 2).mean((1, 2)).cpu().tolist()
        if rows["window"]:
            out[name] = rows
    return out


def run_one(
    entry: Entry, seed: int, budget: Budget, args, run_dir: Path, extra: tuple[str, ...] = ()
) -> dict:
    """Train one model, evaluate it, keep its per-window errors in ``window_errors.json`` (written last:
    its presence marks the run complete)."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.eval.eval_command import run_evaluation
    from mmf_rl.eval.report import write_json
    from mmf_rl.trainers.train_command import train

    errors_path = run_dir / "eval" / "window_errors.json"
    if run_dir.exists():  # an interrupted run: start it again
        import shutil

        shutil.rmtree(run_dir)
    start = time.perf_counter()
    train(compose_config("train", train_overrides(entry, seed, budget, args, run_dir, extra)))
    trained = time.perf_counter() - start
    summary = run_evaluation(
        compose_config(
            "eval",
            [
                f"checkpoint={run_dir}",
                "plots=false",
                "num_samples=0",
                f"device={args.device}",
                f"out_dir={run_dir / 'eval'}",
                f"seed={seed}",
            ],
        )
    )
    errors = window_errors(run_dir, args.device)
    for name, rows in errors.items():
        mse = statistics.fmean(rows["squared_error"])
        reported = summary["subsets"][name]["mse"]
        if abs(mse - reported) > 1e-4 * max(abs(reported), 1e-8) + 1e-7:
            raise RuntimeError(
                f"{run_dir}: subset {name}: the per-window errors average {mse:.6g} but "
                f"run_evaluation reports MSE {reported:.6g}; the two passes disagree on windows "
                "or normalisation"
            )
    total = time.perf_counter() - start
    step_seconds = budget.batch_size / training_rate(run_dir)
    result = {
        "train_seconds": trained,
        "seconds": total,
        "step_seconds": step_seconds,
        "jobs": args.jobs,  # runs trained at once: their per-run times overlap
        "steps": budget.steps,
        "batch_size": budget.batch_size,
        "constant_velocity": summary.get("constant_velocity"),
        "subsets": errors,
    }
    write_json(errors_path, result)  # last: its presence marks the run complete
    print(
        f"  {entry.label} {' '.join(extra)} seed {seed}: trained {budget.steps} steps in {trained:.0f} s "
        f"({1e3 * step_seconds:.0f} ms/step in the training loop), "
        f"total with setup and evaluation {total:.0f} s",
        flush=True,
    )
    return result


def training_rate(run_dir: Path) -> float:
    """Samples per second of the whole training loop: the last ``train/samples_per_s`` the trainer
    logged (csv logger), which counts from the first step to the last."""
    path = run_dir / "logs" / "scalars" / "train" / "samples_per_s.csv"
    rows = path.read_text().split()
    if not rows:
        raise RuntimeError(f"{path} is empty: the training logged no throughput")
    return float(rows[-1].split(",")[1])


def retrained_subsets(budget: Budget) -> list[tuple[str, dict[str, bool]]]:
    return [
        (name, subset)
        for name, subset in subsets()[1:]
        if budget.retrained_subsets == "all" or name in PAPER_SUBSETS
    ]


def run_plan(entry: Entry, budget: Budget, out: Path) -> list[tuple[Entry, int, Path, tuple[str, ...], str]]:
    """The runs behind one entry's cells: ``(entry trained, seed, run_dir, extra overrides, subset)``;
    ``subset`` is the one a retrained run's cell comes from, ``""`` when every subset counts."""
    plan = []
    for seed in budget.seeds:
        if entry.kind != "retrained":
            plan.append((entry, seed, out / slug(entry.label) / f"seed{seed}", (), ""))
            continue
        base = next(e for e in ENTRIES if e.label == entry.base)
        plan.append((base, seed, out / slug(base.label) / f"seed{seed}", (), "all"))
        for name, subset in retrained_subsets(budget):
            dropped = tuple(f"+data.missing.{m}=1.0" for m, kept in subset.items() if not kept)
            plan.append((entry, seed, out / slug(entry.label) / name / f"seed{seed}", dropped, name))
    return plan


def completed(run_dir: Path) -> dict | None:
    path = run_dir / "eval" / "window_errors.json"
    return json.loads(path.read_text()) if path.is_file() else None


def run_pending(entries: list[Entry], budget: Budget, args) -> tuple[int, int]:
    """Train and score every run the entries need that no earlier invocation completed, ``--jobs`` at
    a time; returns (runs needed, runs reused)."""
    runs = {}
    for entry in entries:
        for trained, seed, run_dir, extra, _ in run_plan(entry, budget, args.out):
            runs.setdefault(run_dir, (trained, seed, run_dir, extra))
    pending = [task for run_dir, task in runs.items() if completed(run_dir) is None]
    if args.jobs == 1:
        for trained, seed, run_dir, extra in pending:
            run_one(trained, seed, budget, args, run_dir, extra)
    else:
        # Small models use two threads poorly (the matmul-peak ratio of model_throughput.py): one thread
        # a run and one run a core keeps both cores busy. Each run writes only its own run_dir.
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        threads = max(1, (os.cpu_count() or 1) // args.jobs)
        with ProcessPoolExecutor(
            args.jobs,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=torch.set_num_threads,
            initargs=(threads,),
        ) as pool:
            futures = [
                pool.submit(run_one, trained, seed, budget, args, run_dir, extra)
                for trained, seed, run_dir, extra in pending
            ]
            for future in futures:
                future.result()  # a failed run stops the benchmark with its error
    return len(runs), len(runs) - len(pending)


def entry_results(entry: Entry, budget: Budget, out: Path) -> tuple[dict[str, list[dict]], list[dict]]:
    """``({subset: [errors of each seed]}, [the entry's own runs' window_errors.json])``."""
    per_subset: dict[str, list[dict]] = {}
    runs = []
    for trained, _, run_dir, _, subset in run_plan(entry, budget, out):
        result = completed(run_dir)
        if trained is entry:
            runs.append(result)
        for name, rows in result["subsets"].items():
            if subset in ("", name):
                per_subset.setdefault(name, []).append(rows)
    return per_subset, runs


def entry_coverage(entry: Entry, budget: Budget, out: Path) -> tuple[dict[str, float], bool]:
    """``({subset: 90% interval coverage, mean over seeds}, every run recalibrated)`` from the
    evaluations ``run_one`` wrote (``<run>/eval/results.json``), with each run's scale as it stored it
    (recalibrated per presence pattern on val when its training did: ``mmf-rl train calibrate=true``)."""
    per_subset: dict[str, list[float]] = {}
    recalibrated = True
    for _, _, run_dir, _, subset in run_plan(entry, budget, out):
        scores = json.loads((run_dir / "eval" / "results.json").read_text())
        recalibrated &= scores.get("scale_calibration") is not None
        for name, row in scores["subsets"].items():
            if subset in ("", name) and row.get("coverage_90") is not None:
                per_subset.setdefault(name, []).append(row["coverage_90"])
    return {name: statistics.fmean(values) for name, values in per_subset.items()}, recalibrated


def entry_kl(entry: Entry, budget: Budget, out: Path) -> float | None:
    """The KL of the posterior to the prior in nats with every sensor, mean over seeds (``None`` for a
    model without a latent): near zero, the latent has collapsed."""
    values = []
    for _, _, run_dir, _, subset in run_plan(entry, budget, out):
        row = json.loads((run_dir / "eval" / "results.json").read_text())["subsets"].get("all", {})
        if subset in ("", "all") and row.get("kl") is not None:
            values.append(row["kl"])
    return statistics.fmean(values) if values else None


def kl_section(kl: dict[str, float | None]) -> str:
    rows = [f"| {label} | {value:.2f} |" for label, value in kl.items() if value is not None]
    if not rows:
        return ""
    return (
        "## Latent: KL(q(z|X[,y]) || p(z|X)) on test, every sensor (nats, mean over seeds)\n\n"
        "What the latent carries beyond its prior; near zero it has collapsed and a forecast does not "
        "depend on it.\n\n| entry | KL |\n|---|---|\n" + "\n".join(rows) + "\n\n"
    )


def coverage_table(coverage: dict[str, tuple[dict[str, float], bool]], subsets: Sequence[str]) -> str:
    """Entries as rows: the 90% coverage per subset, how many subsets are in ``COVERAGE_TARGET``, and
    whether the scale was recalibrated."""
    low, high = COVERAGE_TARGET
    lines = [
        "| entry | " + " | ".join(subset_title(s) for s in subsets) + f" | in {low:.2f}-{high:.2f} | scale |",
        "|---" * (len(subsets) + 3) + "|",
    ]
    for label, (cells, recalibrated) in coverage.items():
        inside = sum(low <= cells[s] <= high for s in subsets if s in cells)
        lines.append(
            f"| {label} | "
            + " | ".join(f"{cells[s]:.3f}" if s in cells else "" for s in subsets)
            + f" | {inside}/{sum(s in cells for s in subsets)} | "
            + ("recalibrated on val" if recalibrated else "as trained")
            + " |"
        )
    return "\n".join(lines)


def build_table(
    errors: dict[str, dict[str, list[dict]]],
    kinds: dict[str, str],
    modalities: Sequence[str] = MODALITIES,
    unit: str = "episode",
) -> tuple[Table, list[int]]:
    """Cells with paired bootstrap intervals from every entry's per-window errors; the bootstrap
    resamples the groups of windows ``rows[unit]`` names (test episodes by default). Returns the table
    and the groups."""
    groups = sorted(
        {
            e
            for per_subset in errors.values()
            for seeds in per_subset.values()
            for rows in seeds
            for e in rows[unit]
        }
    )
    weights = bootstrap_weights(len(groups))
    names = [name for name, _ in subsets(modalities)]
    table = Table(subsets=ordered_subsets(names), kinds=dict(kinds))
    for label, per_subset in errors.items():
        table.cells[label] = {
            name: bootstrap_cell(
                [episode_totals(r[unit], r["squared_error"], groups) for r in seeds], weights
            )
            for name, seeds in per_subset.items()
        }
    return table, groups


# ---------------------------------------------------------------------------------------------
# Report.
# ---------------------------------------------------------------------------------------------


def subset_title(name: str) -> str:
    kept = dict(subsets())[name]
    return "+".join(m for m in ("image", "force", "proprio") if kept[m]) + (
        "" if name == "all" else f" ({name})"
    )


def cell_text(cell: Cell | None, bold: bool, tied: bool) -> str:
    if cell is None:
        return ""
    text = f"{cell.mean:.4f} [{cell.low:.4f}, {cell.high:.4f}]"
    return f"**{text}**" if bold else f"{text} =" if tied else text


def fusion_verdicts(table: Table, differences: dict[str, dict]) -> str:
    """One paragraph per prior: the paired all-modality differences against the attention fusion and
    whether attention beats every other fusion beyond the interval (Table 4's claim)."""
    text = ""
    for kind in ("fusion", "learned fusion"):
        rivals = {label: c for label, c in differences.items() if table.kinds[label] == kind}
        if rivals:
            reference = next(iter(rivals.values()))["reference"]
            beats = all(c["high"] < 0 for c in rivals.values())
            text += (
                f"Paired difference {reference} - fusion ablation, all modalities: "
                + differences_text(rivals)
                + ". Attention better than every other fusion beyond the interval: "
                + f"{'yes' if beats else 'no'}.\n\n"
            )
    return text


def differences_text(differences: dict[str, dict]) -> str:
    """``label: difference [low, high]; ...`` of paired differences (``paired_comparisons``' cells)."""
    return "; ".join(
        f"{label}: {c['difference']:+.4f} [{c['low']:+.4f}, {c['high']:+.4f}]"
        for label, c in differences.items()
    )


def mse_table(
    table: Table, labels: list[str], contenders: list[str], title: Callable[[str], str] = subset_title
) -> str:
    """Subsets as rows (named by ``title``), entries as columns; bold: best of ``contenders``, ``=``: any
    entry tied with it."""
    lines = ["| subset | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    for s in table.subsets:
        present = {label: table.cells[label][s] for label in contenders if s in table.cells[label]}
        best = min(present, key=lambda label: present[label].mean) if present else None
        cells = [
            cell_text(
                table.cells[label].get(s),
                label == best,
                best is not None
                and s in table.cells[label]
                and overlap(table.cells[label][s], present[best]),
            )
            for label in labels
        ]
        lines.append(f"| {title(s)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def degradation_table(table: Table, labels: list[str], title: Callable[[str], str] = subset_title) -> str:
    lines = ["| subset | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    for s in table.subsets[1:]:
        lines.append(
            f"| {title(s)} | "
            + " | ".join(
                f"{100 * table.degradation(label, s):+.0f}%" if s in table.cells[label] else ""
                for label in labels
            )
            + " |"
        )
    lines.append(
        "| mean | " + " | ".join(f"{100 * table.mean_degradation(label):+.0f}%" for label in labels) + " |"
    )
    return "\n".join(lines)


def timing(runs: dict[str, list[dict]]) -> dict[str, dict[str, float]]:
    """Per entry: measured ms per training step (the training loop), the rest of a run (data and model
    setup, validation, checkpoint, evaluation) in seconds, and how many runs were trained at once while
    they were measured (``--jobs``; results written before it was recorded count as 1)."""
    out = {}
    for label, results in runs.items():
        if results:
            out[label] = {
                "ms_per_step": 1e3 * statistics.fmean(r["step_seconds"] for r in results),
                "other_seconds": statistics.fmean(
                    r["seconds"] - r["steps"] * r["step_seconds"] for r in results
                ),
                "runs": len(results),
                "batch_size": results[0]["batch_size"],
                "jobs": statistics.fmean(r.get("jobs", 1) for r in results),
            }
    return out


def runs_per_seed(entry: Entry, budget: Budget) -> int:
    return len(retrained_subsets(budget)) if entry.kind == "retrained" else 1


def projection(measured: dict[str, dict[str, float]], budget: Budget) -> tuple[float, list[str]]:
    """Wall seconds the ``budget`` would take from the measured per-step times and per-run overheads
    (recording excluded), and the entries not measured at its batch size. Runs measured ``jobs`` at a
    time overlapped: each adds its time divided by ``jobs`` (summing them would count the overlap twice)."""
    seconds, missing = 0.0, []
    for entry in ENTRIES:
        if budget.entries is not None and entry.label not in budget.entries:
            continue
        m = measured.get(entry.label) or measured.get(entry.base or "")
        if m is None or m["batch_size"] != budget.batch_size:
            missing.append(entry.label)
            continue
        per_run = budget.steps * m["ms_per_step"] / 1e3 + m["other_seconds"]
        seconds += per_run / m.get("jobs", 1) * runs_per_seed(entry, budget) * len(budget.seeds)
    return seconds, missing


def markdown(
    table: Table,
    budget: Budget,
    mode: str,
    info: dict,
    measured: dict,
    comparisons: dict,
    coverage: dict[str, tuple[dict[str, float], bool]] | None = None,
    kl: dict[str, float | None] | None = None,
) -> str:
    seeds = ", ".join(map(str, budget.seeds))
    recorded = (
        f" (recorded in this run in {info['record_seconds']:.0f} s)"
        if info["record_seconds"] is not None
        else ""
    )
    cv = info["constant_velocity_mse"]
    reference = (
        f"Reference: constant-velocity extrapolation of the object's past position (not a model input), "
        f"MSE {cv:.4f}; predicting the training mean gives about 1.\n\n"
        if cv is not None
        else ""
    )
    main_labels = table.labels("paper", "variant", "zero-fill", "retrained")
    contenders = table.labels("paper", "zero-fill", "retrained")
    ablation_labels = ["paper", *table.labels("fusion", "ablation")]
    text = (
        f"# Missing-modality benchmark ({mode} mode)\n\n"
        f"Push dataset {info['data']}: {info['episodes']} episodes{recorded}, "
        "split by episode (split_seed 0), "
        f"{info['test_episodes']} test episodes; images {budget.image_size}x{budget.image_size}, H = T = 10. "
        f"Every model: {budget.steps} steps of batch {budget.batch_size}, seeds {seeds}"
        + ("" if budget.retrained_subsets == "all" else "; retrained baselines only for the paper's subsets")
        + f". Wall time {info['seconds'] / 60:.1f} min"
        + (
            f" for the {info['runs'] - info['reused']} of {info['runs']} runs not reused "
            "from an earlier invocation"
            if info["reused"]
            else ""
        )
        + ".\n\n"
        f"## Test MSE (normalised target): mean over seeds [{LEVEL:.0%} interval]\n\n"
        f"Intervals: percentile bootstrap over the {info['test_episodes']} test episodes "
        f"({BOOTSTRAP_RESAMPLES} resamples, one generator seeded {BOOTSTRAP_SEED}, "
        "the same resamples for every entry, seed and subset); "
        "they cover test-set sampling, not seed variation (per-seed values in results.json). "
        "Bold: lowest mean among the paper model and the baselines; "
        "`=`: interval overlaps the bold one (tied).\n\n"
        + mse_table(table, main_labels, contenders)
        + "\n\n"
        + reference
    )
    if len(ablation_labels) > 1:
        text += (
            "## Ablations of the paper model (Tables 4, 5)\n\n"
            "Bold: lowest mean of the row; `=`: tied with it.\n\n"
            + mse_table(table, ablation_labels, ablation_labels)
            + "\n\n"
        )
    learned_fusion = table.labels("learned fusion")
    if learned_fusion:
        learned_labels = [reference_of(learned_fusion[0], "learned fusion"), *learned_fusion]
        text += (
            "## Table 4 under the learned prior\n\n"
            "With the standard prior a forecast is decoded at z = 0, so the fusion acts only in training; "
            "with the learned prior it gives p(z|X), which every forecast is decoded from.\n\n"
            + mse_table(table, learned_labels, learned_labels)
            + "\n\n"
        )
    text += (
        "## Relative degradation (MSE / MSE with all modalities - 1)\n\n"
        + degradation_table(table, [*main_labels, *ablation_labels[1:], *learned_fusion])
        + "\n\n"
    )
    text += fusion_verdicts(table, comparisons.get("all", {}))
    if coverage:
        text += (
            "## Calibration: 90% interval coverage on test (mean over seeds)\n\n"
            f"Issue #13's target: {COVERAGE_TARGET[0]:.2f}-{COVERAGE_TARGET[1]:.2f} in every subset. The "
            "paper model and its variants are scored at their eval latent (default: the prior's mean).\n\n"
            + coverage_table(coverage, table.subsets)
            + "\n\n"
        )
    text += kl_section(kl or {})
    text += (
        "## Run time\n\n"
        f"Window cache built or opened once before the trainings in {info['cache_seconds']:.0f} s. "
        "Per entry, measured by each run when it trained (a reused run keeps its times): the training "
        "loop's time per step and the rest of a run (data and model setup, validation, checkpoint, "
        "evaluation).\n\n"
        "| entry | runs timed | runs at once | training ms/step | rest of a run (s) "
        "|\n|---|---|---|---|---|\n"
    )
    text += (
        "\n".join(
            f"| {label} | {m['runs']} | {m['jobs']:g} | {m['ms_per_step']:.0f} | {m['other_seconds']:.0f} |"
            for label, m in measured.items()
        )
        + "\n\n"
    )
    for name, target in (("standard", STANDARD), ("full", FULL)):
        seconds, missing = projection(measured, target)
        if len(missing) == sum(target.entries is None or e.label in target.entries for e in ENTRIES):
            continue  # nothing measured at its batch size
        text += (
            f"Projected {name} mode ({target.steps} steps of batch {target.batch_size}, "
            f"{len(target.seeds)} seeds, as many runs at once as measured, "
            f"recording excluded) from these times: {seconds / 60:.0f} min"
            + (
                f" for the entries measured; not measured at batch {target.batch_size}: {', '.join(missing)}"
                if missing
                else ""
            )
            + ".\n\n"
        )
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode_flags = parser.add_mutually_exclusive_group()
    for name in ("tiny", "quick", "standard"):
        mode_flags.add_argument(
            f"--{name}", action="store_true", help=f"the {name.upper()} budget in this file"
        )
    parser.add_argument(
        "--data",
        type=Path,
        default=None,
        help="recorded push dataset (default data/push_bench_<episodes>ep; recorded if absent)",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="runs and results (default runs/bench_accuracy_<mode>)"
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="override the mode's seeds")
    parser.add_argument("--steps", type=int, default=None, help="override the mode's training steps")
    parser.add_argument("--batch-size", type=int, default=None, help="override the mode's batch size")
    parser.add_argument(
        "--entries",
        nargs="+",
        default=None,
        help="override the mode's entries (labels; must include 'paper')",
    )
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (passed to train and eval)")
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="runs trained at once, each with cores/jobs threads (2 on 2 cores: see run_pending)",
    )
    args = parser.parse_args(argv)
    from mmf_rl.eval.report import write_json, write_text

    if args.jobs < 1:
        parser.error(f"--jobs must be >= 1, found {args.jobs}")
    mode = next((name for name in ("tiny", "quick", "standard") if getattr(args, name)), "full")
    budget = MODES[mode]
    if args.entries is not None:
        unknown = sorted(set(args.entries) - {e.label for e in ENTRIES})
        if unknown or "paper" not in args.entries:
            parser.error(
                f"--entries: unknown {unknown} or 'paper' missing; entries are {[e.label for e in ENTRIES]}"
            )
    budget = Budget(
        budget.image_size,
        args.batch_size or budget.batch_size,
        args.steps or budget.steps,
        tuple(args.seeds) if args.seeds else budget.seeds,
        tuple(args.entries) if args.entries else budget.entries,
        budget.episodes,
        budget.retrained_subsets,
    )
    args.out = (args.out or REPO / "runs" / f"bench_accuracy_{mode}").resolve()
    args.data = (args.data or REPO / "data" / f"push_bench_{budget.episodes}ep").resolve()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    entries = [e for e in ENTRIES if budget.entries is None or e.label in budget.entries]
    check_entries(entries, budget, args)

    start = time.perf_counter()
    record_seconds = None if args.data.exists() else record_dataset(args.data, budget.episodes)
    cache_seconds = build_cache(budget, args)
    args.runs, args.reused = run_pending(entries, budget, args)  # the wall time covers the runs not reused
    errors, runs, kinds, coverage, kl = {}, {}, {}, {}, {}
    for entry in entries:
        errors[entry.label], runs[entry.label] = entry_results(entry, budget, args.out)
        kinds[entry.label] = entry.kind
        coverage[entry.label] = entry_coverage(entry, budget, args.out)
        kl[entry.label] = entry_kl(entry, budget, args.out)
    seconds = time.perf_counter() - start

    table, test_episodes = build_table(errors, kinds)
    line, summary = summarize(table)
    comparisons = paired_comparisons(table)
    measured = timing(runs)
    cv = next(
        (
            r["constant_velocity"]["mse"]
            for results in runs.values()
            for r in results
            if r.get("constant_velocity")
        ),
        None,
    )
    info = {
        "data": str(args.data),
        "episodes": _episode_count(args.data),
        "test_episodes": len(test_episodes),
        "record_seconds": record_seconds,
        "cache_seconds": cache_seconds,
        "seconds": seconds,
        "runs": args.runs,
        "reused": args.reused,
        "constant_velocity_mse": cv,
    }
    text = markdown(table, budget, mode, info, measured, comparisons, coverage, kl) + f"{line}\n"
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "results.md", text)
    write_json(
        args.out / "results.json",
        {
            "mode": mode,
            "budget": budget.__dict__,
            "info": info,
            "kinds": kinds,
            "subsets": table.subsets,
            "test_episodes": test_episodes,
            "bootstrap": {"resamples": BOOTSTRAP_RESAMPLES, "seed": BOOTSTRAP_SEED, "level": LEVEL},
            "cells": {
                label: {s: c.to_dict() for s, c in cells.items()} for label, cells in table.cells.items()
            },
            "paired_differences": comparisons,
            "timing": measured,
            "coverage_90": {label: cells for label, (cells, _) in coverage.items()},
            "kl": kl,
            "summary": summary,
        },
    )
    print(text)
    return 0


def _episode_count(root: Path) -> int | None:
    """``total_episodes`` of the LeRobot dataset's ``meta/info.json``."""
    info = root / "meta" / "info.json"
    return json.loads(info.read_text()).get("total_episodes") if info.is_file() else None


if __name__ == "__main__":
    from mmf_rl.cli import configure_logging

    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    sys.exit(main())
