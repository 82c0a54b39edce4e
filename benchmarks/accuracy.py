"""Missing-modality accuracy benchmark on the recorded push dataset (paper Tables 3, 4, 5).

    .venv/bin/python benchmarks/accuracy.py --quick        # ~25 min on 2 shared cores (see QUICK below)
    .venv/bin/python benchmarks/accuracy.py                # the full benchmark (see FULL below)

Every entry is trained with the same step budget, batch size and seeds on the same recording
(fixed train/val/test episodes: ``data.split_seed``) with ``mmf-rl train``'s ``train(cfg)``, then
scored on every presence subset of the test split with ``mmf-rl eval``'s ``run_evaluation(cfg)``.
The metric is MSE on the normalised target (MultiBench's push metric).

Entries:

* ``paper``: the attention CVAE, trained once on all modalities (ELBO + ``L_mis``).
* Baselines, two protocols for absent modalities at test time:
  - trained once on all modalities: ``LF-LSTM`` and ``MulT`` see an absent modality as zeros
    (zero-fill), ``MVAE`` drops its expert from the product (its native handling);
  - ``(retrained)``: the paper's protocol, one model per subset trained with only that subset's
    modalities present (``+data.missing.<m>=1.0`` for the others); its ``all`` cell is the model
    trained on all modalities.
* Ablations of the paper's model: the multimodal encoder replaced by ``linear``, ``average``,
  ``sum``, ``cross_attention`` fusion (Table 4); without ``L_mis`` (``loss=no_mis``) and trained
  with 50 % of the image samples missing (Table 5); and, to separate the image encoder from the
  fusion, the paper model with the baselines' per-frame image encoder (``conv_gru``).

The dataset is recorded if ``--data`` does not exist (120 episodes x 50 steps at 64x64, 2
workers). Completed runs (``<out>/<entry>/seed<k>/eval/results.json``) are reused, so an
interrupted benchmark resumes; delete ``--out`` to start over. Writes ``<out>/results.md`` and
``<out>/results.json`` and ends with one line:
``summary: paper model best in X/Y subsets; mean degradation paper P%, best baseline Q%``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ["force", "image", "proprio"]


@dataclass(frozen=True)
class Budget:
    image_size: int
    batch_size: int
    steps: int
    seeds: tuple[int, ...]
    entries: tuple[str, ...] | None  # None: every entry


# Quick: 32x32 images (the cache resizes the 64x64 recording), 2 seeds, 300 steps of batch 32, the
# paper model, the three baselines trained on all modalities and the L_mis ablation; the retrained
# baselines (18 extra runs per seed) and the fusion / missing-data ablations are left out.
# Measured: 25 min on 2 cores shared with other jobs (load 4-6); single runs took 7 s to 11 min
# depending on that load. 300 steps is ~3 epochs: too few for a stable ranking (see the report).
QUICK = Budget(image_size=32, batch_size=32, steps=300, seeds=(0, 1),
               entries=("paper", "paper w/o L_mis", "LF-LSTM", "MVAE", "MulT"))
# Full: every entry (14; 29 trainings per seed), 3 seeds, 2000 steps of batch 64 at 32x32 (MultiBench's
# gentle_push image size; the per-frame ConvNets of LF-LSTM and MulT cost 4x more at 64x64).
# Measured here: every entry at 1000 steps of batch 32, 3 seeds (87 trainings), took 83 min on 2 cores
# (~57 s a training, MulT and LF-LSTM the slowest); FULL trains 4x the samples a run, so ~6 h in all.
# Not run on the 2-core development machine; meant for a GPU (--device auto) or a long night.
FULL = Budget(image_size=32, batch_size=64, steps=2000, seeds=(0, 1, 2), entries=None)


@dataclass(frozen=True)
class Entry:
    label: str
    kind: str  # "paper" | "baseline" | "ablation"
    overrides: tuple[str, ...]
    retrained: bool = False  # one run per presence subset (the paper's protocol for baselines)
    base: str | None = None  # the entry whose all-modality run gives a retrained entry's "all" cell


ENTRIES = [
    Entry("paper", "paper", ("model=forecaster",)),
    Entry("LF-LSTM", "baseline", ("model=lf_lstm",)),
    Entry("MVAE", "baseline", ("model=mvae",)),
    Entry("MulT", "baseline", ("model=mult",)),
    Entry("LF-LSTM (retrained)", "baseline", ("model=lf_lstm",), retrained=True, base="LF-LSTM"),
    Entry("MVAE (retrained)", "baseline", ("model=mvae",), retrained=True, base="MVAE"),
    Entry("MulT (retrained)", "baseline", ("model=mult",), retrained=True, base="MulT"),
    Entry("paper fusion=linear", "ablation", ("model=forecaster", "model.fusion=linear")),
    Entry("paper fusion=average", "ablation", ("model=forecaster", "model.fusion=average")),
    Entry("paper fusion=sum", "ablation", ("model=forecaster", "model.fusion=sum")),
    Entry("paper fusion=cross_attention", "ablation", ("model=forecaster", "model.fusion=cross_attention")),
    Entry("paper w/o L_mis", "ablation", ("model=forecaster", "loss=no_mis")),
    Entry("paper, 50% image missing in training", "ablation", ("model=forecaster", "+data.missing.image=0.5")),
    # Not in the paper: the image encoder MulT and LF-LSTM use (a ConvNet per frame, then a GRU)
    # instead of the default frame-stacked ConvNet, to tell the encoder from the fusion.
    Entry("paper, per-frame image encoder", "ablation",
          ("model=forecaster", "data.modalities.image={feature:observation.images.front,encoder:conv_gru}")),
]


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text).strip("_").lower()


def record_dataset(root: Path) -> float:
    """Record the benchmark's push dataset with ``mmf-rl record``; returns the wall time."""
    start = time.perf_counter()
    cmd = [sys.executable, "-m", "mmf_rl.cli", "record", "--out", str(root), "--episodes", "120", "--workers", "2",
           "--image-size", "64", "--steps", "50", "--seed", "0"]
    print("recording:", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    return time.perf_counter() - start


def subsets() -> list[tuple[str, dict[str, bool]]]:
    from mmf_rl.datasets import presence_subsets

    return list(presence_subsets(MODALITIES))


def run_one(entry: Entry, seed: int, budget: Budget, args, run_dir: Path, extra: tuple[str, ...] = ()) -> dict:
    """Train one model and evaluate it on every subset; returns ``{subset: mse}``."""
    from mmf_rl.configuration import compose_config
    from mmf_rl.eval.run import run_evaluation
    from mmf_rl.trainers.run import train

    results_path = run_dir / "eval" / "results.json"
    args.runs += 1
    if results_path.is_file():
        args.reused += 1
        return {name: m["mse"] for name, m in json.loads(results_path.read_text())["subsets"].items()}
    if run_dir.exists():  # an interrupted run: start it again
        import shutil

        shutil.rmtree(run_dir)
    overrides = [
        *entry.overrides, *extra,
        f"data.root={args.data}", f"data.cache_dir={args.out / 'cache'}", f"data.image_size=[{budget.image_size},{budget.image_size}]",
        f"run_dir={run_dir}", f"trainer.total_steps={budget.steps}", f"trainer.batch_size={budget.batch_size}",
        f"trainer.seed={seed}", f"trainer.eval_every={budget.steps}", f"trainer.checkpoint_every={budget.steps}",
        f"trainer.warmup_steps={min(100, budget.steps // 10)}", f"loss.kl_warmup_steps={min(200, budget.steps // 5)}",
        "trainer.keep_checkpoints=1", "trainer.progress_bar=false", "logger=csv", "num_workers=2",
        f"device={args.device}",
    ]
    start = time.perf_counter()
    train(compose_config("train", overrides))
    trained = time.perf_counter() - start
    summary = run_evaluation(compose_config("eval", [f"checkpoint={run_dir}", "plots=false", "num_samples=0",
                                                     f"device={args.device}",
                                                     f"out_dir={run_dir / 'eval'}", f"seed={seed}"]))
    print(f"  {entry.label} {' '.join(extra)} seed {seed}: trained {budget.steps} steps in {trained:.0f} s, "
          f"total {time.perf_counter() - start:.0f} s", flush=True)
    return {name: m["mse"] for name, m in summary["subsets"].items()}


def run_entry(entry: Entry, budget: Budget, args) -> dict[str, list[float]]:
    """``{subset: [mse per seed]}`` for one entry."""
    cells: dict[str, list[float]] = {}
    for seed in budget.seeds:
        if not entry.retrained:
            for name, mse in run_one(entry, seed, budget, args, args.out / slug(entry.label) / f"seed{seed}").items():
                cells.setdefault(name, []).append(mse)
            continue
        base = next(e for e in ENTRIES if e.label == entry.base)
        cells.setdefault("all", []).append(
            run_one(base, seed, budget, args, args.out / slug(base.label) / f"seed{seed}")["all"])
        for name, subset in subsets()[1:]:
            dropped = tuple(f"+data.missing.{m}=1.0" for m, kept in subset.items() if not kept)
            run_dir = args.out / slug(entry.label) / name / f"seed{seed}"
            mse = run_one(entry, seed, budget, args, run_dir, dropped)[name]
            cells.setdefault(name, []).append(mse)
    return cells


@dataclass
class Table:
    names: list[str]
    rows: dict[str, dict[str, list[float]]] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)

    def mean(self, label: str, subset: str) -> float:
        return statistics.fmean(self.rows[label][subset])

    def std(self, label: str, subset: str) -> float:
        values = self.rows[label][subset]
        return statistics.stdev(values) if len(values) > 1 else 0.0

    def degradation(self, label: str, subset: str) -> float:
        """Relative MSE increase against the same entry with all modalities."""
        return self.mean(label, subset) / self.mean(label, "all") - 1

    def mean_degradation(self, label: str) -> float:
        return statistics.fmean(self.degradation(label, s) for s in self.names if s != "all")


def constant_velocity_mse(args) -> float | None:
    """The constant-velocity extrapolation of the object's own past (not a model input) on the test split:
    a reference any useful model should beat. Every run's evaluation stores it; they are identical."""
    for path in sorted(args.out.glob("*/seed*/eval/results.json")):
        reference = json.loads(path.read_text()).get("constant_velocity")
        if reference:
            return reference["mse"]
    return None


def markdown(table: Table, budget: Budget, seconds: float, record_seconds: float | None, mode: str,
             cv_mse: float | None, reused: int, runs: int) -> str:
    head = "| entry | " + " | ".join(table.names) + " |\n|---|" + "---|" * len(table.names) + "\n"
    mse_rows, degradation_rows = [], []
    for label in table.rows:
        best = {s: min(table.mean(lab, s) for lab in table.rows if table.kinds[lab] != "ablation")
                for s in table.names}
        cells = []
        for s in table.names:
            text = f"{table.mean(label, s):.4f} ± {table.std(label, s):.4f}"
            cells.append(f"**{text}**" if table.kinds[label] != "ablation" and table.mean(label, s) == best[s] else text)
        mse_rows.append(f"| {label} | " + " | ".join(cells) + " |")
        degradation_rows.append(f"| {label} | " + " | ".join(f"{100 * table.degradation(label, s):+.0f}%"
                                                             for s in table.names[1:])
                                + f" | {100 * table.mean_degradation(label):+.0f}% |")
    seeds = ", ".join(map(str, budget.seeds))
    recorded = f" (recorded in this run in {record_seconds:.0f} s)" if record_seconds is not None else ""
    reference = (f"Reference: constant-velocity extrapolation of the object's past position (not a model input), "
                 f"MSE {cv_mse:.4f}; predicting the training mean gives about 1.\n\n" if cv_mse is not None else "")
    return (
        f"# Missing-modality benchmark ({mode} mode)\n\n"
        f"Push dataset: 120 episodes x 50 steps{recorded}, train/val/test split by episode (split_seed 0); "
        f"images {budget.image_size}x{budget.image_size}, H = T = 10. Every model: {budget.steps} steps of batch "
        f"{budget.batch_size}, seeds {seeds}. Wall time {seconds / 60:.1f} min"
        + (f" for the {runs - reused} of {runs} runs not reused from an earlier invocation" if reused else "")
        + ".\n\n"
        "## Test MSE (normalised target), mean ± std over seeds\n\n"
        "Bold: best of the paper model and the baselines (ablations excluded) in each subset.\n\n"
        + head + "\n".join(mse_rows) + "\n\n" + reference
        + "## Relative degradation (MSE / MSE with all modalities - 1)\n\n"
        "| entry | " + " | ".join(table.names[1:]) + " | mean |\n|---|" + "---|" * len(table.names) + "\n"
        + "\n".join(degradation_rows) + "\n"
    )


def summarize(table: Table) -> tuple[str, dict]:
    baselines = [label for label, kind in table.kinds.items() if kind == "baseline"]
    if not baselines:
        return "summary: no baseline among the entries", {}
    best = within_std = 0
    for s in table.names:
        paper = table.mean("paper", s)
        best_baseline = min(baselines, key=lambda lab: table.mean(lab, s))
        best += paper <= table.mean(best_baseline, s)
        within_std += paper <= table.mean(best_baseline, s) + max(table.std("paper", s), table.std(best_baseline, s))
    paper_deg = table.mean_degradation("paper")
    best_baseline_deg = min(table.mean_degradation(lab) for lab in baselines)
    line = (f"summary: paper model best in {best}/{len(table.names)} subsets; mean degradation paper "
            f"{100 * paper_deg:.0f}%, best baseline {100 * best_baseline_deg:.0f}%")
    return line, {"best": best, "within_one_std": within_std, "subsets": len(table.names),
                  "paper_mean_degradation": paper_deg, "best_baseline_mean_degradation": best_baseline_deg}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="the ~20 min budget (QUICK in this file)")
    parser.add_argument("--data", type=Path, default=REPO / "data" / "push_bench", help="recorded push dataset")
    parser.add_argument("--out", type=Path, default=None, help="runs and results (default runs/bench_accuracy[_quick])")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, help="override the mode's seeds")
    parser.add_argument("--steps", type=int, default=None, help="override the mode's training steps")
    parser.add_argument("--entries", nargs="+", default=None, help="override the mode's entries (labels; must include 'paper')")
    parser.add_argument("--device", default="cpu", help="cpu | cuda | auto (passed to train and eval)")
    args = parser.parse_args(argv)
    from mmf_rl.eval.report import write_json, write_text

    budget = QUICK if args.quick else FULL
    if args.entries is not None:
        unknown = sorted(set(args.entries) - {e.label for e in ENTRIES})
        if unknown or "paper" not in args.entries:
            parser.error(f"--entries: unknown {unknown} or 'paper' missing; entries are {[e.label for e in ENTRIES]}")
    if args.seeds is not None or args.steps is not None or args.entries is not None:
        budget = Budget(budget.image_size, budget.batch_size, args.steps or budget.steps,
                        tuple(args.seeds) if args.seeds else budget.seeds,
                        tuple(args.entries) if args.entries else budget.entries)
    mode = "quick" if args.quick else "full"
    args.out = (args.out or REPO / "runs" / f"bench_accuracy_{mode}").resolve()
    args.data = args.data.resolve()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")

    start = time.perf_counter()
    args.runs = args.reused = 0  # counted by run_one: the wall time covers only the runs not reused
    record_seconds = None if args.data.exists() else record_dataset(args.data)
    entries = [e for e in ENTRIES if budget.entries is None or e.label in budget.entries]
    table = Table(names=[name for name, _ in subsets()])
    for entry in entries:
        print(f"{entry.label}:", flush=True)
        table.rows[entry.label] = run_entry(entry, budget, args)
        table.kinds[entry.label] = entry.kind
    seconds = time.perf_counter() - start

    line, summary = summarize(table)
    text = markdown(table, budget, seconds, record_seconds, mode, constant_velocity_mse(args), args.reused, args.runs)
    if summary:
        text += (f"\nPaper model best in {summary['best']}/{summary['subsets']} subsets, best or within one std of "
                 f"the best baseline in {summary['within_one_std']}/{summary['subsets']}.\n")
    text += f"\n{line}\n"
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "results.md", text)
    write_json(args.out / "results.json",
               {"mode": mode, "budget": budget.__dict__, "seconds": seconds, "record_seconds": record_seconds,
                "runs": args.runs, "reused_runs": args.reused, "mse": table.rows, "kinds": table.kinds,
                "summary": summary})
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
