"""Calibration of the forecast's scale by eval latent: trained runs re-evaluated, nothing retrained.

    .venv/bin/python benchmarks/calibration.py RUN_DIR [RUN_DIR ...] --out /tmp/calibration
    .venv/bin/python benchmarks/calibration.py bench/acc_std/paper*/seed* --latents mean predictive

The question: the learned prior's point forecast, decoded at the prior's mean, is as
accurate as the standard prior's, but its Gaussian scale was trained on posterior draws that know
the future and its 90% intervals cover far less than 90% of test futures. Does the moment-matched
predictive (``eval_latent=predictive``: the mean and variance of the mixture of the decodes of
``K`` prior draws, ``ForecasterConfig.predictive_samples``) give calibrated intervals without
costing point accuracy?

Every run directory (a ``mmf-rl train`` run) is scored by ``mmf_rl.evaluate`` (``mmf-rl eval``) on
its own test split (``--split``: choose settings such as ``--predictive-samples`` on ``val``),
on every presence subset, once per ``--latents`` entry (``as-trained`` keeps
the run's own ``eval_latent``), with ``--num-samples`` prior samples for minMSE@K. Runs are grouped
by their parent directory's name (``acc_std/paper_prior_learned/seed0`` -> ``paper_prior_learned``:
the seeds of one benchmark entry); each cell is the mean over the group's runs. The evaluations
are written under ``--out/<group>/<run>/<latent>/``; a re-run reuses the finished ones.

``--recalibrate`` answers the next question (the target: the 90% interval covers 80-97% of
test futures in every presence subset): does a per-presence-pattern scale recalibration on the
validation split (``mmf-rl calibrate``) get there? For each run and latent it writes copies of
the model under ``--out/<group>/<run>/<latent>/`` (``save_pretrained``; the run itself is not
touched): ``raw``, its scale factors reset to ones (the scale as trained), and one per
``--methods`` entry (``levels``, the default fit: the 90% factor and a level curve per pattern;
``coverage``, the 90% factor alone; ``temperature``, the NLL-optimal one),
fitted by it on the run's val split with ``--min-windows``; each is scored on ``--split``, as the
rows ``<latent>:raw`` and ``<latent>:<method>``.

Writes ``--out/results.md`` and ``results.json``; ends with one ``summary:`` line per group and
latent: the all-sensor MSE, the range over subsets of the 50% and 90% interval coverage (a
calibrated scale: 0.5 and 0.9), and of the 90% intervals' mean width (target units) and the CRPS
(normalised): of two rows covering alike, the narrower, lower-CRPS one is the better.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

from mmf_rl.eval.report import write_json, write_text
from mmf_rl.eval.scale_fit import CALIBRATION_METHODS, DEFAULT_METHOD

METRICS = (
    ("mse", "MSE", "{:.4f}"),
    ("min_mse_k", "minMSE@K", "{:.4f}"),
    ("nll", "NLL", "{:.1f}"),
    ("coverage_50", "cover 50%", "{:.2f}"),
    ("coverage_90", "cover 90%", "{:.2f}"),
    ("width_90", "width 90%", "{:.3g}"),
    ("crps", "CRPS", "{:.4f}"),
)


def evaluate(run_dir: Path, latent: str, args, out_dir: Path | None = None) -> dict:
    """``mmf_rl.evaluate``'s summary of ``run_dir`` (a run or a saved model) under ``latent`` (reused
    when already written), into ``out_dir`` (default ``--out/<group>/<run>/<latent>``)."""
    import mmf_rl

    out_dir = out_dir or args.out / run_dir.parent.name / run_dir.name / latent
    done = out_dir / "results.json"
    if done.is_file():
        return json.loads(done.read_text())
    overrides = [
        f"checkpoint={run_dir}",
        f"out_dir={out_dir}",
        "allow_outside_run_dir=true",
        "plots=false",
        f"num_samples={args.num_samples}",
        f"device={args.device}",
        f"split={args.split}",
    ]
    if latent != "as-trained":
        overrides.append(f"eval_latent={latent}")
    if latent == "predictive":
        overrides.append(f"predictive_samples={args.predictive_samples}")
    started = time.perf_counter()
    summary = mmf_rl.evaluate(overrides=overrides)
    print(f"  {run_dir} {latent}: {time.perf_counter() - started:.0f} s", flush=True)
    return summary


def has_eval_latent(run_dir: Path) -> bool:
    """Whether the run's model has an ``eval_latent`` setting (the forecaster, MVAE; not MulT, LF-LSTM):
    checked before any scoring, so that a latent is not refused halfway through the runs."""
    import yaml

    from mmf_rl.models.registry import DEFAULT_MODEL, config_settings, model_entry

    name = (yaml.safe_load((run_dir / "config.yaml").read_text()).get("model") or {}).get(
        "name", DEFAULT_MODEL
    )
    return "eval_latent" in config_settings(model_entry(name).config_cls)


def recalibrated_copies(run_dir: Path, latent: str, args) -> dict[str, Path]:
    """The run's model under ``latent`` as the ``raw`` copy and one per ``--methods`` entry (see the
    module docstring), written once under ``--out``; the run is only read."""
    from mmf_rl.eval.calibration import calibrate
    from mmf_rl.models import load_trained_model
    from mmf_rl.models.hub import CALIBRATION_FILE

    base = args.out / run_dir.parent.name / run_dir.name / latent
    copies = {variant: base / variant for variant in ("raw", *args.methods)}
    if (copies["raw"] / "config.json").is_file() and all(
        (copies[method] / CALIBRATION_FILE).is_file() for method in args.methods
    ):
        return copies
    overrides = {}
    if latent != "as-trained":
        overrides["eval_latent"] = latent
    if latent == "predictive":
        overrides["predictive_samples"] = args.predictive_samples
    model, _, _ = load_trained_model(run_dir, config_overrides=overrides)
    model.scale_calibration.reset()
    model.calibration = None
    for path in copies.values():
        model.save_pretrained(path)
    for method in args.methods:
        calibrate(
            overrides=[
                f"checkpoint={copies[method]}",
                f"method={method}",
                f"min_windows={args.min_windows}",
                f"device={args.device}",
            ]
        )
    return copies


def group_table(rows: dict[str, dict[str, list[dict]]]) -> dict[str, dict[str, dict[str, float]]]:
    """``{latent: {subset: {metric: mean over runs}}}`` from ``{latent: {run: summary}}``."""
    table: dict[str, dict[str, dict[str, float]]] = {}
    for latent, summaries in rows.items():
        subsets = summaries[0]["subsets"]
        table[latent] = {
            subset: {
                metric: statistics.fmean(s["subsets"][subset][metric] for s in summaries)
                for metric, _, _ in METRICS
                if metric in subsets[subset]
            }
            for subset in subsets
        }
    return table


def summary_lines(tables: dict[str, dict]) -> list[str]:
    lines = []
    for group, table in tables.items():
        for latent, subsets in table.items():
            cover = {level: [row[f"coverage_{level}"] for row in subsets.values()] for level in ("50", "90")}
            lines.append(
                f"summary: {group} {latent}: MSE all {subsets['all']['mse']:.4f}; "
                f"coverage 50% {min(cover['50']):.2f}-{max(cover['50']):.2f}, "
                f"90% {min(cover['90']):.2f}-{max(cover['90']):.2f} over {len(subsets)} subsets"
                + sharpness(subsets)
            )
    return lines


def sharpness(subsets: dict[str, dict[str, float]]) -> str:
    """The summary's ranges of the 90% width and the CRPS ("" for evaluations written before them)."""
    if any("crps" not in row for row in subsets.values()):
        return ""
    width = [row["width_90"] for row in subsets.values()]
    crps = [row["crps"] for row in subsets.values()]
    return f"; width 90% {min(width):.3g}-{max(width):.3g}, CRPS {min(crps):.4f}-{max(crps):.4f}"


def markdown(tables: dict[str, dict], runs: dict[str, list[str]], args, minutes: float) -> str:
    parts = [
        "# Calibration by eval latent\n",
        f"`benchmarks/calibration.py` — {minutes:.1f} min; {args.split} split; K = {args.num_samples} "
        f"samples for minMSE@K; predictive: {args.predictive_samples} prior draws. Each cell: mean over the "
        "group's runs. 'width 90%' is in target units, CRPS on the normalised target."
        + (
            " `<latent>:raw`: the scale as trained; `<latent>:<method>`: recalibrated per presence "
            f"pattern on the val split by that method (min_windows={args.min_windows})."
            if args.recalibrate
            else ""
        )
        + "\n",
    ]
    for group, table in tables.items():
        parts.append(f"\n## {group}\n\nRuns: {', '.join(f'`{r}`' for r in runs[group])}\n")
        header = "| subset | latent | " + " | ".join(title for _, title, _ in METRICS) + " |"
        parts += [header, "|" + "---|" * (len(METRICS) + 2)]
        subsets = next(iter(table.values())).keys()
        for subset in subsets:
            for latent, rows in table.items():
                row = rows[subset]
                cells = [fmt.format(row[m]) if m in row else "-" for m, _, fmt in METRICS]
                parts.append(f"| {subset} | {latent} | " + " | ".join(cells) + " |")
    return "\n".join(parts) + "\n\n" + "\n".join(summary_lines(tables)) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run directories of `mmf-rl train`")
    parser.add_argument("--latents", nargs="+", default=["mean", "predictive"])
    parser.add_argument("--predictive-samples", type=int, default=16)
    parser.add_argument("--num-samples", type=int, default=20, help="K of minMSE@K (0: skip)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--split",
        default="test",
        choices=["train", "val", "test"],
        help="choose settings on val, report test",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/bench_calibration"))
    parser.add_argument(
        "--recalibrate",
        action="store_true",
        help="score each latent with its scale as trained (raw) and recalibrated per presence pattern on val",
    )
    parser.add_argument(
        "--min-windows", type=int, default=32, help="--recalibrate: mmf-rl calibrate's min_windows"
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        default=[DEFAULT_METHOD],
        choices=sorted(CALIBRATION_METHODS),
        help="--recalibrate: mmf-rl calibrate's methods, one recalibrated copy each",
    )
    args = parser.parse_args(argv)
    unknown = sorted(set(args.latents) - {"as-trained", "mean", "sample", "predictive"})
    if unknown:
        parser.error(f"--latents: unknown {unknown}; choose among as-trained, mean, sample, predictive")
    missing = [str(r) for r in args.runs if not (r / "checkpoints").is_dir()]
    if missing:
        parser.error(f"not `mmf-rl train` run directories (no checkpoints/ inside): {missing}")
    latentless = [str(r) for r in args.runs if not has_eval_latent(r)]
    if latentless and set(args.latents) != {"as-trained"}:
        parser.error(
            f"--latents {' '.join(args.latents)}: these runs' models have no eval latent: {latentless}; "
            "score them with --latents as-trained (in an invocation of their own, or with every run)"
        )

    started = time.perf_counter()
    groups: dict[str, dict[str, list[dict]]] = {}
    runs: dict[str, list[str]] = {}
    for run_dir in args.runs:
        group = run_dir.parent.name
        runs.setdefault(group, []).append(str(run_dir))
        for latent in args.latents:
            if not args.recalibrate:
                groups.setdefault(group, {}).setdefault(latent, []).append(evaluate(run_dir, latent, args))
                continue
            for variant, copy in recalibrated_copies(run_dir, latent, args).items():
                # The copy's config holds the latent: it is scored as saved.
                summary = evaluate(copy, "as-trained", args, out_dir=copy / "eval")
                groups.setdefault(group, {}).setdefault(f"{latent}:{variant}", []).append(summary)
    tables = {group: group_table(rows) for group, rows in groups.items()}
    minutes = (time.perf_counter() - started) / 60
    text = markdown(tables, runs, args, minutes)
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / "results.md", text)
    write_json(args.out / "results.json", {"runs": runs, "tables": tables, "minutes": minutes})
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
