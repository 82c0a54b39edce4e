"""ETH/UCY: can a forecast scale calibrated without the test scene hold its intervals on that scene?

    mmf-rl bench ethucy_calibration --data data/ethucy --out runs/bench_ethucy_calibration

The paper model with the ETH/UCY benchmark's quick recipe (``benchmarks.pedestrians.recipe.QUICK``, no
option selected) is trained on each of the five leave-one-scene-out folds and on each of the ten pairs
of held-out scenes (`benchmarks.pedestrians.sealed`: three training scenes). Then:

1. **The scale each scene needs.** For each pair model and each scene it holds out: the 90%
   split-conformal factor of its standardised errors there with every modality present
   (:func:`~mmf_rl.eval.scale_fit.coverage_factor`), as a scene's range over the four models that hold
   it out. A factor that depends on the scene, not on the model, is a shift no fit on other scenes
   can know.
2. **Two fits, scored once on the test scene.** Each fold's model gets the default ``levels`` fit
   (:mod:`mmf_rl.eval.scale_fit`) on its val split (windows of its four training scenes, what
   ``mmf-rl train`` does), and, as a cross-fit, on the pooled standardised errors of its four pair
   models on their held-out training scenes (:func:`~mmf_rl.eval.scale_fit.fit_to_errors`). Each is
   scored on the test scene in the benchmark's four modes: 50% and 90% coverage, 90% width (m), CRPS.

Completed runs under ``--out`` are reused when their recipe is this one (as ``bench ethucy`` checks
them); ``--out`` can be a ``bench ethucy --quick`` output. A ``bench ethucy --select`` output is refused
when the selection chose an option the paper model reads (its fold rows record the choice, which this
recipe does not make), though its inner runs of the unselected values would serve as the pair models.
Writes ``<out>/calibration.md`` and ``<out>/calibration.json``; ends with one line: ``summary: test 90%
coverage (val | held-out scenes fit) FOLD a-b | c-d ...; within 0.85-0.95: N | M of 5 folds; 90% factor
each scene needs: SCENE x-y ...``.
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import replace
from pathlib import Path

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import ethucy as bench  # noqa: E402
from benchmarks.pedestrians.recipe import PAPER, QUICK, completed, run_path, stale_run  # noqa: E402
from benchmarks.pedestrians.runs import fold_config, fold_data, scene_data  # noqa: E402
from benchmarks.pedestrians.scoring import MODES  # noqa: E402
from benchmarks.pedestrians.sealed import inner_run, write_held_out_configs  # noqa: E402
from benchmarks.pedestrians.selection import held_out_pairs, inner_splits, pair_scenes  # noqa: E402

logger = logging.getLogger("mmf_rl.benchmarks.ethucy_calibration")

FITS = ("val", "held-out scenes")
NOMINAL_90 = (0.85, 0.95)  # the band #54 asks of every subset's test 90% coverage
MIN_WINDOWS = 32
INTERVAL_METRICS = ("coverage_50", "coverage_90", "width_90", "crps")  # the table's columns, in order


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """``bench ethucy``'s arguments for its quick recipe, from this script's own."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--raw", type=Path, default=bench.REPO.parent / "shared" / "data" / "ethucy")
    parser.add_argument("--data", type=Path, default=bench.REPO / "data" / "ethucy", help="converted dataset")
    parser.add_argument("--out", type=Path, default=bench.REPO / "runs" / "bench_ethucy_calibration")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--batch-size", type=int, default=512, help="evaluation batch size")
    own = parser.parse_args(argv)
    forwarded = ["--raw", own.raw, "--data", own.data, "--out", own.out, "--device", own.device]
    return bench.parse_args(["--quick", *map(str, forwarded), "--batch-size", str(own.batch_size)])


def train_all(args: argparse.Namespace) -> None:
    """Every fold's model and every pair's, trained unless completed; completed runs of another recipe
    refused before anything trains."""
    from mmf_rl.datasets.ethucy import FOLDS

    budget = replace(QUICK, folds=tuple(FOLDS))
    runs = [(fold, None) for fold in FOLDS] + [(pair, {}) for pair in held_out_pairs(FOLDS, FOLDS)]
    if stale := [line for line in (stale_run(args, budget, run, PAPER, c) for run, c in runs) if line]:
        raise SystemExit(
            f"ethucy_calibration: runs of another recipe in {args.out}:\n  " + "\n  ".join(stale)
        )
    bench.ensure_data(args, tuple(FOLDS))
    write_held_out_configs(args, budget)
    for run, candidate in runs:
        if candidate is not None:
            inner_run(args, budget, run, PAPER, candidate)
        elif completed(args, run, PAPER) is None:
            # As `bench ethucy` trains and scores a fold's row: its scores.json is that benchmark's, which
            # reuses it (a record without the scores would break its table).
            bench.run_trained(args, budget, run, PAPER, fold_data(args, run)[0])


def held_out_errors(args: argparse.Namespace) -> dict[tuple[str, str], object]:
    """``{(pair, scene): StandardisedErrors}`` of each pair model on each scene it holds out."""
    from mmf_rl.datasets.ethucy import FOLDS
    from mmf_rl.eval.scale_fit import standardised_errors
    from mmf_rl.models import load_trained_model

    errors = {}
    for pair in held_out_pairs(FOLDS, FOLDS):
        model, _, _ = load_trained_model(
            run_path(args, pair, PAPER, {}) / "checkpoints", map_location=args.device
        )
        for scene in pair_scenes(pair):
            data = scene_data(args, fold_config(args, pair), scene)
            loader = data.loader("test", args.batch_size, shuffle=False)
            errors[pair, scene] = standardised_errors(model, loader, args.device)
    return errors


def scene_factors(errors: dict) -> dict[str, list[float]]:
    """``{scene: [90% factor of each model holding it out]}``, every modality present."""
    from mmf_rl.eval.scale_fit import coverage_factor

    factors: dict[str, list[float]] = {}
    for (_, scene), found in errors.items():
        every_modality = (1 << len(found.names)) - 1  # the pattern index with every bit set
        factors.setdefault(scene, []).append(coverage_factor(found.magnitudes[every_modality].flatten()))
    return factors


def score_fits(args: argparse.Namespace, fold: str, errors: dict) -> dict[str, dict[str, dict]]:
    """``{fit: {mode: {coverage_50, coverage_90, width_90, crps}}}`` of ``fold``'s model on its test scene
    after each fit of `FITS`."""
    from mmf_rl.datasets.ethucy import FOLDS
    from mmf_rl.eval.metrics import evaluate_presence_subsets
    from mmf_rl.eval.scale_fit import fit_scale_calibration, fit_to_errors
    from mmf_rl.models import load_trained_model

    model, _, _ = load_trained_model(run_path(args, fold, PAPER) / "checkpoints", map_location=args.device)
    data, _ = fold_data(args, fold)
    pooled = None
    for pair, scene in inner_splits(FOLDS, fold):
        pooled = errors[pair, scene] if pooled is None else pooled.pooled(errors[pair, scene])
    modes = [(mode, MODES[mode]) for mode in MODES]
    scores = {}
    for fit in FITS:
        if fit == "val":
            val = data.loader("val", args.batch_size, shuffle=False)
            fit_scale_calibration(model, val, MIN_WINDOWS, args.device, "levels")
        else:
            fit_to_errors(model, pooled, MIN_WINDOWS, "levels")
        test = data.loader("test", args.batch_size, shuffle=False)
        rows, _ = evaluate_presence_subsets(
            model, test, modes, data.normalizer.denormalize_target, device=args.device
        )
        scores[fit] = {m: {k: rows[m][k] for k in INTERVAL_METRICS} for m in rows}
    return scores


def span(values) -> str:
    values = list(values)
    return f"{min(values):.2f}-{max(values):.2f}"


def markdown(factors: dict[str, list[float]], folds: dict[str, dict]) -> str:
    lines = [
        "# ETH/UCY: calibrated intervals on the held-out scene",
        "",
        "The 90% factor each scene needs when held out (every modality present; over the four pair models):",
        "",
        "| scene | factor |",
        "|---|---|",
        *(f"| {scene} | {span(values)} |" for scene, values in sorted(factors.items())),
        "",
        "Test scene, ranges over the four modes:",
        "",
        "| fold | fit | 50% | 90% | width 90% (m) | CRPS (norm.) |",
        "|---|---|---|---|---|---|",
    ]
    for fold, by_fit in folds.items():
        for fit, rows in by_fit.items():
            cells = [span(r[k] for r in rows.values()) for k in INTERVAL_METRICS]
            lines.append(f"| {fold} | {fit} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def summary(factors: dict[str, list[float]], folds: dict[str, dict]) -> str:
    def within(rows) -> bool:
        return all(NOMINAL_90[0] <= r["coverage_90"] <= NOMINAL_90[1] for r in rows.values())

    cover = " ".join(
        f"{fold} " + " | ".join(span(r["coverage_90"] for r in by_fit[fit].values()) for fit in FITS)
        for fold, by_fit in folds.items()
    )
    met = " | ".join(str(sum(within(by_fit[fit]) for by_fit in folds.values())) for fit in FITS)
    needed = " ".join(f"{scene} {span(values)}" for scene, values in sorted(factors.items()))
    return (
        f"summary: test 90% coverage ({' | '.join(FITS)} fit) {cover}; "
        f"within {NOMINAL_90[0]}-{NOMINAL_90[1]}: {met} of {len(folds)} folds; "
        f"90% factor each scene needs: {needed}"
    )


def main(argv: list[str] | None = None) -> int:
    from mmf_rl.configuration import write_text_atomic
    from mmf_rl.datasets.ethucy import FOLDS
    from mmf_rl.eval.report import write_json
    from mmf_rl.log import configure_logging

    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    args = parse_args(argv)
    train_all(args)
    errors = held_out_errors(args)
    factors = scene_factors(errors)
    folds = {fold: score_fits(args, fold, errors) for fold in FOLDS}
    write_json(args.out / "calibration.json", {"scene_factors_90": factors, "test": folds})
    page = markdown(factors, folds)
    write_text_atomic(args.out / "calibration.md", page)
    print(page)
    print(summary(factors, folds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
