"""Missing-sensor accuracy on a real humanoid recording: the paper model against the baselines.

    .venv/bin/python benchmarks/real_humanoid.py --jobs 2    # every entry x 2 seeds, two runs at once
    .venv/bin/python benchmarks/real_humanoid.py --steps 2 --seeds 0 --entries paper LF-LSTM --batch-size 4

Run time: see results.md (it records the measured wall time of every run and of the invocation).

Data: a Unitree G1 recording in LeRobot v3.0 (default: the 6-episode slice g1_pick_bottle_small of the
shared data, found like the tests find it: ``$MMF_RL_SHARED_DATA`` or ``../shared/data`` beside the
repository). Three sensors: the head camera ``observation.images.cam_high`` (96x128 AV1 video, read at
32x32), the 26 joint positions ``observation.state`` and the 26 joint commands ``action``. The target
is the joints' motion: ``observation.state`` relative to the last observed frame, all 26 dims, over
the next T = 10 frames from H = 10 frames of history. One split by episode (split_fractions 0.8 / 0.1
/ 0.1, split_seed 0) for every model.

Entries (``ENTRIES``): the paper model with the configuration defaults, with the other prior, with GRU
encoders for joints and commands, with its decoder reading the fusion's mixed tokens and the camera as
one token per frame, and with the pair-stream decoder over per-step tokens of joints and commands and a
linear latent (the push benchmark's closest entry to MulT), and with ``L_mis``'s teacher detached (no
gradient through its full-input side; the default trains it end to end, as the paper does); the
baselines LF-LSTM, MulT and MVAE, each trained once on every sensor and seeing an absent sensor as its
own absence handling (zero-fill; MVAE drops the expert), and each of them trained for missing sensors
(modality dropout drawn every batch, ``L_mis`` beside its own term, or both), with the paper model
with modality dropout too. Every entry: ``--steps`` steps of batch
``--batch-size`` for each seed, trained with ``mmf_rl.train`` (``mmf-rl train``) and scored on every
presence subset of the test split with ``mmf_rl.evaluate`` (``mmf-rl eval``). The machinery
(training, per-window errors, the paired bootstrap, the tables, the summary) is ``mmf_rl.compare``'s;
only the data, the entries and the report are this file's.

Each cell: normalised test MSE, mean over seeds, with a 95% paired bootstrap interval (the same
resamples for every entry, seed and sensor subset). With at least ``MIN_EPISODES`` test episodes the
bootstrap resamples test episodes; with fewer (the slice has one) an episode bootstrap says nothing,
so it resamples blocks of ``BLOCK`` consecutive test windows of an episode (a non-overlapping block
bootstrap: windows of non-adjacent blocks share no frame): that interval is over the test episode's
stretches of motion, not over episodes or recordings. results.md says which was used and how many
test episodes, windows and blocks there are.

Completed runs (``<out>/<entry>/seed<k>/eval/window_errors.json``) are reused, so an interrupted
benchmark resumes; a reused run trained with other steps or batch size is refused. An entry whose label
changes is trained again under its new directory: move the old one to keep its runs
(``paper_gru_vector_encoders__issue__6`` is now ``paper__gru_vector_encoders``). Writes
``<out>/results.md`` and ``<out>/results.json`` and ends with one line:
``summary: all sensors paper MSE A vs best baseline B (NAME): paper/best = R (target <= 1.05); mean
degradation without a sensor paper P%, best baseline Q%`` (``-`` where the run lacks what a number
needs). The best baseline is the one with the lowest all-sensor MSE; the baseline degradation is the
lowest mean degradation among the baselines (the most robust one, named in results.md).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from mmf_rl.compare import entries as catalogue
from mmf_rl.compare import report, script
from mmf_rl.compare.bootstrap import (
    BOOTSTRAP_RESAMPLES,
    BOOTSTRAP_SEED,
    LEVEL,
    Table,
    bootstrap_unit,
    build_table,
)
from mmf_rl.compare.entries import BASELINE_KINDS, Entry, Study, select_entries, subsets
from mmf_rl.compare.summary import paired_comparisons, summarize_against_best_baseline

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("MMF_RL_SHARED_DATA", REPO.parent / "shared" / "data"))
DEFAULT_ROOT = SHARED_DATA / "g1_pick_bottle_small"
IMAGE_SIZE = 32
HISTORY = HORIZON = 10
MODALITIES = ["cam_high", "state", "action"]
SENSORS = {"cam_high": "camera", "state": "joints", "action": "commands"}
TARGET_RATIO = 1.05  # the target: paper all-sensor MSE within 5% of the best baseline's
MIN_EPISODES = 10  # fewer test episodes: bootstrap blocks of windows instead of episodes
BLOCK = HISTORY + HORIZON  # windows a block: one window's span of frames (stride 1)

# The data config `mmf-rl inspect` suggests for the recording (its three sensors), with the target and
# window of the humanoid protocol. The root, cache and image size come from mmf_rl.compare's train_overrides.
DATA = (
    "data.repo_id=local/g1_pick_bottle_small",
    "data.target={feature:observation.state,relative:true}",
    f"data.history={HISTORY}",
    f"data.horizon={HORIZON}",
    "data.split_fractions=[0.8,0.1,0.1]",
    "data.split_seed=0",
)
SENSOR_FEATURES = (
    "data.modalities={cam_high:{feature:observation.images.cam_high},"
    "state:{feature:observation.state},action:{feature:action}}"
)
# The same with the GRU sequence encoder for the vector sensors (the default is now "mlp"), as one
# mapping (SENSOR_FEATURES + data.modalities.state.encoder=gru ... composes the same config).
SENSOR_FEATURES_GRU = (
    "data.modalities={cam_high:{feature:observation.images.cam_high},"
    "state:{feature:observation.state,encoder:gru},action:{feature:action,encoder:gru}}"
)
ENTRIES = [
    Entry("paper", "paper", (*DATA, SENSOR_FEATURES, "model=forecaster")),
    Entry(
        "paper prior=learned",
        "variant",
        (*DATA, SENSOR_FEATURES, "model=forecaster", "model.prior=learned"),
    ),
    Entry("paper, GRU vector encoders", "variant", (*DATA, SENSOR_FEATURES_GRU, "model=forecaster")),
    Entry(
        "paper, mixed tokens, per-frame camera tokens",
        "variant",
        (
            *DATA,
            SENSOR_FEATURES,
            "model=forecaster",
            "model.decoder_input=mixed",
            "data.modalities.cam_high.encoder=conv_frames",
        ),
    ),
    Entry(
        "paper, pair-stream decoder, linear z, per-step vector tokens",
        "variant",
        (
            *DATA,
            SENSOR_FEATURES,
            "model=forecaster",
            "model.decoder_input=pair_streams",
            "model.decoder_latent=linear",
            "data.modalities.state.encoder=steps",
            "data.modalities.action.encoder=steps",
        ),
    ),
    # The default trains L_mis end to end, as the paper does; this stops its gradient through the
    # full-input side.
    Entry(
        "paper, L_mis teacher detached",
        "ablation",
        (*DATA, SENSOR_FEATURES, "model=forecaster", "loss.detach_teacher=true"),
    ),
    Entry("LF-LSTM", "zero-fill", (*DATA, SENSOR_FEATURES, "model=lf_lstm")),
    Entry("MulT", "zero-fill", (*DATA, SENSOR_FEATURES, "model=mult")),
    Entry("MVAE", "zero-fill", (*DATA, SENSOR_FEATURES, "model=mvae")),
    # The baselines trained for missing sensors (modality dropout, L_mis, both) and the paper model with
    # modality dropout too: the catalogue's entries on this recording's data.
    *(
        Entry(e.label, e.kind, (*DATA, SENSOR_FEATURES, *e.overrides))
        for e in (*catalogue.TRAINED_FOR_MISSING, catalogue.PAPER_DROPOUT)
    ),
]


def subset_title(name: str) -> str:
    """``without_cam_high`` -> ``without camera``; ``only_state`` -> ``joints only``."""
    if name == "all":
        return "all sensors"
    how, modality = name.split("_", 1)
    sensor = SENSORS.get(modality, modality)
    return f"without {sensor}" if how == "without" else f"{sensor} only"


# ---------------------------------------------------------------------------------------------
# Report.
# ---------------------------------------------------------------------------------------------


def run_times(runs: dict[str, list[dict]], info: dict) -> str:
    lines = [
        "| entry | seed | training (s) | run with setup and evaluation (s) | training ms/step |",
        "|---|---|---|---|---|",
    ]
    for label, results in runs.items():
        for seed, r in zip(info["seeds"], results, strict=True):
            lines.append(
                f"| {label} | {seed} | {r['train_seconds']:.0f} | {r['seconds']:.0f} | "
                f"{1e3 * r['step_seconds']:.0f} |"
            )
    return (
        "## Run time\n\n"
        "Measured on the machine that wrote this file; window cache built or opened before the trainings "
        f"in {info['cache_seconds']:.0f} s. A reused run keeps the times of the invocation that trained "
        "it.\n\n" + "\n".join(lines) + "\n\n"
    )


def intro(info: dict) -> str:
    split = info["split"]
    return (
        "# Missing-sensor benchmark on a real humanoid recording\n\n"
        f"Data {info['root']}: {info['episodes']} episodes, split by episode (split_fractions 0.8 / 0.1 / "
        f"0.1, split_seed 0): train {split['train']}, val {split['val']}, test {split['test']} "
        f"({info['test_windows']} test windows). Sensors: camera (observation.images.cam_high at "
        f"{IMAGE_SIZE}x{IMAGE_SIZE}), joints (observation.state, 26-D), commands (action, 26-D); target: "
        f"the joints' motion (observation.state relative to the last observed frame, 26 dims), "
        f"H = {HISTORY}, T = {HORIZON}. Every model: {info['steps']} steps of batch {info['batch_size']}, "
        f"seeds {', '.join(map(str, info['seeds']))}. Wall time of this invocation "
        f"{info['seconds'] / 60:.1f} min"
        + (f" ({info['reused']} of {info['runs']} runs reused from an earlier one)" if info["reused"] else "")
        + ".\n\n"
    )


def target_text(summary: dict) -> str:
    ratio = summary["paper_over_best"]
    paper_deg = summary["paper_mean_degradation_without_a_sensor"]
    baseline_deg = summary["best_baseline_mean_degradation_without_a_sensor"]
    text = "## Target\n\n"
    if ratio is None:
        return text + "No baseline in this run: the target cannot be judged.\n\n"
    text += (
        f"All sensors: paper / best baseline ({summary['best_baseline']}) = {ratio:.3f}, target <= "
        f"{TARGET_RATIO}: {'met' if summary['ratio_target_met'] else 'NOT met'}. "
    )
    if paper_deg is not None and baseline_deg is not None:
        text += (
            f"Robustness, mean degradation without one sensor: paper {100 * paper_deg:+.0f}%, most "
            f"robust baseline ({summary['most_robust_baseline']}) {100 * baseline_deg:+.0f}%: the "
            f"paper model {'keeps' if paper_deg <= baseline_deg else 'does NOT keep'} its robustness "
            "advantage."
        )
    return text + "\n\n"


def markdown(table: Table, info: dict, runs: dict, summary: dict, comparisons: dict) -> str:
    labels = list(table.kinds)
    cv = info["constant_velocity_mse"]
    text = (
        intro(info)
        + "## Test MSE (normalised target): mean over seeds [95% interval]\n\n"
        + report.intervals_text(info["unit"], info["groups"], info["split"]["test"], BLOCK)
        + "\n\n"
        + report.mse_table(table, labels, table.labels("paper", *BASELINE_KINDS), title=subset_title)
        + "\n\n"
        + (
            f"Reference: constant-velocity extrapolation of the joints, MSE {cv:.4f}; predicting the "
            "training mean gives about 1.\n\n"
            if cv is not None
            else ""
        )
        + "## Relative degradation (MSE / MSE with all sensors - 1)\n\n"
        + report.degradation_table(table, labels, title=subset_title)
        + "\n\nThe mean row averages every subset above; the summary line's degradation averages the "
        "three without-one-sensor rows.\n\n"
    )
    paper_all = comparisons.get("all", {})
    if paper_all:
        text += (
            "Paired difference paper - baseline, all sensors: " + report.differences_text(paper_all) + ".\n\n"
        )
    return text + target_text(summary) + run_times(runs, info)


# ---------------------------------------------------------------------------------------------
# Main.
# ---------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--root", type=Path, default=DEFAULT_ROOT, help=f"the G1 recording (default {DEFAULT_ROOT})"
    )
    parser.add_argument(
        "--out", type=Path, default=REPO / "runs" / "bench_real_humanoid", help="runs and results"
    )
    parser.add_argument("--steps", type=int, default=1000, help="training steps of every run")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    labels = [e.label for e in ENTRIES]
    parser.add_argument(
        "--entries", nargs="+", default=labels, help=f"labels, 'paper' among them (default all: {labels})"
    )
    script.add_run_flags(parser)
    args = parser.parse_args(argv)
    script.check_run_flags(parser, args, ENTRIES)
    args.root = args.root.expanduser().resolve()
    if not (args.root / "meta" / "info.json").is_file():
        parser.error(
            f"--root {args.root}: no LeRobot dataset there (meta/info.json missing); pass the G1 recording's "
            "directory, or set MMF_RL_SHARED_DATA to the shared data directory holding g1_pick_bottle_small"
        )
    return args


def study_of(args: argparse.Namespace) -> Study:
    return Study(
        out=args.out.resolve(),
        budget=catalogue.Budget(args.steps, args.batch_size, tuple(args.seeds), IMAGE_SIZE),
        entries=tuple(select_entries(ENTRIES, args.entries)),
        modalities=tuple(MODALITIES),
        data_overrides=(f"data.root={args.root}",),
        device=args.device,
        jobs=args.jobs,
    )


def results_json(
    study: Study, table: Table, info: dict, runs: dict, comparisons: dict, summary: dict
) -> dict:
    return {
        "info": info,
        "entries": {e.label: {"kind": e.kind, "overrides": list(e.overrides)} for e in study.entries},
        "subsets": table.subsets,
        "bootstrap": {
            "unit": info["unit"],
            "block_windows": BLOCK if info["unit"] == "block" else None,
            "resamples": BOOTSTRAP_RESAMPLES,
            "seed": BOOTSTRAP_SEED,
            "level": LEVEL,
        },
        "cells": report.cells_json(table),
        "paired_differences": comparisons,
        "runs": {
            label: [{k: v for k, v in r.items() if k != "subsets"} for r in rs] for label, rs in runs.items()
        },
        "summary": summary,
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    study = study_of(args)
    script.check_study(study, "real humanoid benchmark")
    outcome = script.run_study(study)
    collected = outcome.collected
    unit = bootstrap_unit(collected.errors, BLOCK, MIN_EPISODES)
    names = [name for name, _ in subsets(MODALITIES)]
    table, groups = build_table(collected.errors, collected.kinds, names, unit=unit)
    line, summary = summarize_against_best_baseline(table, TARGET_RATIO)
    comparisons = paired_comparisons(table)
    info = {
        "root": str(args.root),
        "episodes": script.recorded_episodes(args.root),
        "split": {name: list(map(int, eps)) for name, eps in outcome.data.split_episodes.items()},
        "test_windows": len(outcome.data.split_windows["test"]),
        "unit": unit,
        "groups": groups,
        "steps": args.steps,
        "batch_size": args.batch_size,
        "seeds": list(args.seeds),
        **outcome.info(),
    }
    text = markdown(table, info, collected.runs, summary, comparisons) + f"{line}\n"
    results = results_json(study, table, info, collected.runs, comparisons, summary)
    script.report_results(study.out, text, results)
    return 0


if __name__ == "__main__":
    script.run_as_script(main)
