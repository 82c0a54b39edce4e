"""Missing-modality accuracy benchmark on the recorded push dataset (paper Tables 3, 4, 5).

    .venv/bin/python benchmarks/accuracy.py --standard --jobs 2   # STANDARD_ENTRIES, 3 seeds, 2 runs at once
    .venv/bin/python benchmarks/accuracy.py --quick        # paper model, zero-fill baselines, w/o L_mis
    .venv/bin/python benchmarks/accuracy.py --tiny         # smoke run of the code paths (meaningless numbers)
    .venv/bin/python benchmarks/accuracy.py                # every entry at the full budget (see FULL below)

The protocol is ``mmf_rl.compare`` (``mmf-rl compare`` runs it on any data config): every entry
trained with the same budget and seeds on the same recording, scored on every presence subset of the
test split (MSE on the normalised target, MultiBench's push metric), each cell the mean over seeds
with a 95% paired bootstrap interval over test episodes; "best or tied": the intervals overlap the
best's. This script holds the push benchmark's own part: its entries, budgets and recording.

Entries (``ENTRIES``; a new model option is one line there):

* ``paper``: the attention CVAE with the configuration defaults (ELBO + ``L_mis``); ``variant``
  rows: the same model with one of its options (learned prior, drop distribution, GSNN).
* Baselines, three protocols for absent modalities at test time:
  - ``zero-fill``: trained once on all modalities; ``LF-LSTM`` and ``MulT`` see an absent
    modality as zeros, ``MVAE`` drops its expert from the product (its native handling);
  - ``retrained``: the paper's protocol, one model per subset trained with only that subset's
    modalities present (``+data.missing.<m>=1.0`` for the others); its ``all`` cell is the model
    trained on all modalities;
  - ``trained for missing``: trained once with sensors removed, by modality dropout drawn every batch,
    by ``L_mis`` beside its own term, or both (``mmf_rl.compare.entries.TRAINED_FOR_MISSING``).
* Ablations of the paper's model: ``linear``, ``average``, ``sum``, ``cross_attention`` fusion
  (Table 4), also under the learned prior (``learned fusion``: there the fusion also gives the latent a
  test forecast decodes); without ``L_mis`` and with 50 % of the images missing in training (Table 5);
  ``L_mis`` with its teacher detached (the default trains it end to end, as the paper does);
  the baselines' per-frame image encoder (``conv_gru``), to tell the image encoder from the fusion.

The dataset is recorded if ``--data`` does not exist (the mode's episode count x 50 steps at 64x64).
Completed runs are reused: an interrupted benchmark resumes (delete ``--out`` to start over); a completed
run of other steps or batch size, or whose config differs from the one this build composes for its
entry (a changed default included), is refused (the report says every model trained with one budget and
as its entry says). A run lives in ``<out>/<the entry's label as a slug>/seed<k>``, so an entry whose
label changes is trained again: move the old directory to keep its runs (the check accepts a run moved
to another directory or ``--out``). Writes
``<out>/results.md`` and ``<out>/results.json`` and ends with one line:
``summary: paper model best or tied in X/Y subsets (zero-fill baselines), R/3 paper subsets vs
retrained; fusion spread S; mean degradation paper P%, best baseline Q%`` (``-`` where the run
lacks the entries a number needs).
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from functools import partial
from pathlib import Path

from mmf_rl.compare import entries as catalogue
from mmf_rl.compare import report, script
from mmf_rl.compare.bootstrap import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, LEVEL, Table, build_table
from mmf_rl.compare.collect import Collected, timing
from mmf_rl.compare.entries import Entry, subsets
from mmf_rl.compare.summary import paired_comparisons, summarize

REPO = Path(__file__).resolve().parents[1]
MODALITIES = ["force", "image", "proprio"]
# MuJoCo Push subsets reported in the paper (Table 3): image+force+proprio, image+force, image+proprio.
PAPER_SUBSETS = ("all", "without_proprio", "without_force")
push_subset_title = partial(report.subset_title, modalities=("image", "force", "proprio"))


@dataclass(frozen=True)
class Budget(script.Mode):
    """A mode of this benchmark, which also says the subsets its retrained baselines are trained for."""

    retrained_subsets: str = "all"  # "all" | "paper": the subsets the retrained baselines are trained for


# Budget(image_size, batch_size, steps, seeds, entries, episodes, retrained_subsets).
# Tiny: every code path (each entry kind, seeds averaged, the bootstrap) on a small recording in a few
# minutes; the numbers mean nothing.
TINY_ENTRIES = ("paper", "LF-LSTM", "LF-LSTM (retrained)", "paper fusion=linear", "paper w/o L_mis")
TINY = Budget(32, 8, 4, (0, 1), TINY_ENTRIES, 16, "paper")
# Quick: the paper model, the zero-fill baselines and the L_mis ablation.
QUICK = Budget(32, 32, 300, (0, 1, 2), ("paper", "paper w/o L_mis", "LF-LSTM", "MVAE", "MulT"), 200)
# Standard: the entries that answer the benchmark's question (the paper model, its documented options,
# the baselines in both protocols, Table 4's fusions, Table 5's ablations), 3 seeds, 1000 steps of batch
# 32 at 32x32. The other entries are the searches that chose the defaults: the full mode and `--entries`
# run them. The retrained baselines are trained for the paper's three subsets only (the ones they are
# compared on). results.md gives the wall time and projects this mode's time from the per-step times of
# the run that wrote it.
STANDARD_ENTRIES = (
    catalogue.PAPER.label,
    "paper, decoder reads raw tokens",
    catalogue.PAPER_LEARNED.label,
    "paper eval_latent=posterior",
    "paper, pair-stream decoder, linear z, per-step vector tokens",
    *(e.label for e in (*catalogue.ZERO_FILL, *catalogue.RETRAINED, *catalogue.TRAINED_FOR_MISSING)),
    *(e.label for e in catalogue.FUSION_ABLATIONS),
    catalogue.PAPER_DROPOUT.label,
    catalogue.NO_MIS.label,
    "paper, L_mis teacher detached",
    "paper, 50% image missing in training",
    "paper, per-frame image encoder",
)
STANDARD = Budget(32, 32, 1000, (0, 1, 2), STANDARD_ENTRIES, 200, "paper")
# Full: every entry, the retrained baselines for every subset, 3 seeds, 2000 steps of batch 64 at 32x32
# (MultiBench's gentle_push image size). Meant for a GPU (--device auto) or a long night on 2 cores.
FULL = Budget(32, 64, 2000, (0, 1, 2), None, 200)
MODES = {"tiny": TINY, "quick": QUICK, "standard": STANDARD, "full": FULL}

LEARNED = catalogue.LEARNED
PAPER = ("model=forecaster",)
# The sequence encoder of the earlier model for force and proprioception (the default is now "mlp").
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
# The decoder reads MulT's pair streams, over one token per step of each vector modality.
PAIR_STREAMS = (
    "model.decoder_input=pair_streams",
    "data.modalities.force.encoder=steps",
    "data.modalities.proprio.encoder=steps",
)
# MulT's tokenizer for the vector modalities (a linear layer + ReLU per step) and its pair set (the
# self pairs read only for a lone modality), for the pair-stream decoder.
MULT_PAIRS_AND_STEP_TOKENS = (
    "model.decoder_input=pair_streams",
    "model.pair_self=alone",
    "data.modalities.force.encoder=linear_steps",
    "data.modalities.proprio.encoder=linear_steps",
)
ENTRIES = [
    catalogue.PAPER,
    # Options of the paper model. The defaults (standard prior, MLP window encoders for the vector
    # modalities, L_mis dropping one modality) were chosen from this table; the learned prior's options
    # are measured on top of the learned prior.
    catalogue.PAPER_LEARNED,
    Entry("paper prior=learned, GRU vector encoders", "variant", (*PAPER, *LEARNED, *GRU_VECTORS)),
    Entry("paper prior=learned, drop 1..M-1", "variant", (*PAPER, *LEARNED, "loss.max_dropped=null")),
    Entry("paper prior=learned, GSNN 0.5", "variant", (*PAPER, *LEARNED, "loss.gsnn_weight=0.5")),
    Entry(
        "paper prior=learned, degraded NLL 1.0", "variant", (*PAPER, *LEARNED, "loss.dropped_nll_weight=1.0")
    ),
    Entry("paper, GRU vector encoders", "variant", (*PAPER, *GRU_VECTORS)),
    Entry("paper, drop 1..M-1", "variant", (*PAPER, "loss.max_dropped=null")),
    # The fusion on every test forecast: the paper's decoder reads the encoders' raw tokens, so under
    # the standard prior the fusion acts only in training (the default reads the mixed tokens); or the
    # forecast decodes at q(z|X)'s mean (eqs. 10 and 15); and tokens per step instead of one per modality.
    Entry("paper, decoder reads raw tokens", "variant", (*PAPER, "model.decoder_input=tokens")),
    Entry("paper eval_latent=posterior", "variant", (*PAPER, "model.eval_latent=posterior")),
    Entry(
        "paper, mixed tokens, per-frame image tokens",
        "variant",
        (*PAPER, "model.decoder_input=mixed", "data.modalities.image.encoder=conv_frames"),
    ),
    Entry(
        "paper, mixed tokens, per-step tokens", "variant", (*PAPER, "model.decoder_input=mixed", *STEP_TOKENS)
    ),
    # MulT's pair streams as the decoder's input, on per-step vector tokens (the image keeps its
    # frame-stacked token), with each way z enters the decoder; and the streams over the mixed tokens.
    Entry("paper, pair-stream decoder, per-step vector tokens", "variant", (*PAPER, *PAIR_STREAMS)),
    Entry(
        "paper, pair-stream decoder, linear z, per-step vector tokens",
        "variant",
        (*PAPER, *PAIR_STREAMS, "model.decoder_latent=linear"),
    ),
    Entry(
        "paper, pair-stream decoder, no z, per-step vector tokens",
        "variant",
        (*PAPER, *PAIR_STREAMS, "model.decoder_latent=none"),
    ),
    # The same decoder without z and without L_mis: MulT's objective (the NLL alone) on the paper's
    # architecture, to tell what the CVAE objective costs with every sensor from what the model does.
    Entry(
        "paper, pair-stream decoder, no z, w/o L_mis, per-step vector tokens",
        "variant",
        (*PAPER, *PAIR_STREAMS, "model.decoder_latent=none", "loss=no_mis"),
    ),
    # The image's frames as tokens too (MulT's per-frame ConvNet), with and without the CVAE objective.
    Entry(
        "paper, pair-stream decoder, linear z, per-step tokens for all three",
        "variant",
        (*PAPER, *PAIR_STREAMS, "model.decoder_latent=linear", "data.modalities.image.encoder=conv_frames"),
    ),
    Entry(
        "paper, pair-stream decoder, no z, w/o L_mis, per-step tokens for all three",
        "variant",
        (
            *PAPER,
            *PAIR_STREAMS,
            "model.decoder_latent=none",
            "loss=no_mis",
            "data.modalities.image.encoder=conv_frames",
        ),
    ),
    # MulT's pair set and vector tokenizer in the paper model: with MulT's objective and image tokens (what
    # is left of the architecture), and as the CVAE with z added linearly.
    Entry(
        "paper, MulT's pairs and step tokens, no z, w/o L_mis, per-frame image tokens",
        "variant",
        (
            *PAPER,
            *MULT_PAIRS_AND_STEP_TOKENS,
            "model.decoder_latent=none",
            "loss=no_mis",
            "data.modalities.image.encoder=conv_frames",
        ),
    ),
    Entry(
        "paper, MulT's pairs and step tokens, linear z",
        "variant",
        (*PAPER, *MULT_PAIRS_AND_STEP_TOKENS, "model.decoder_latent=linear"),
    ),
    Entry(
        "paper, pair streams of mixed tokens, linear z, per-step vector tokens",
        "variant",
        (*PAPER, "model.decoder_input=mixed_pair_streams", *PAIR_STREAMS[1:], "model.decoder_latent=linear"),
    ),
    *catalogue.ZERO_FILL,
    *catalogue.RETRAINED,
    *catalogue.TRAINED_FOR_MISSING,
    *catalogue.FUSION_ABLATIONS,
    *catalogue.LEARNED_FUSION_ABLATIONS,
    catalogue.NO_MIS,
    catalogue.PAPER_DROPOUT,
    catalogue.NO_MIS_DROPOUT,
    Entry("paper, L_mis teacher detached", "ablation", (*PAPER, "loss.detach_teacher=true")),
    Entry("paper, 50% image missing in training", "ablation", (*PAPER, "+data.missing.image=0.5")),
    # Not in the paper: the image encoder MulT and LF-LSTM use (a ConvNet per frame, then a GRU)
    # instead of the default frame-stacked ConvNet, to tell the encoder from the fusion.
    Entry(
        "paper, per-frame image encoder",
        "ablation",
        (*PAPER, "data.modalities.image={feature:observation.images.front,encoder:conv_gru}"),
    ),
]


def runs_per_seed(entry: Entry, budget: Budget) -> int:
    if entry.kind != "retrained":
        return 1
    return len(PAPER_SUBSETS) - 1 if budget.retrained_subsets == "paper" else len(subsets(MODALITIES)) - 1


def projection(measured: dict[str, dict[str, float]], budget: Budget) -> tuple[float, list[str]]:
    """Wall seconds the ``budget`` would take from the measured per-step times and per-run overheads
    (recording excluded), and the entries not measured at its batch size. Runs measured ``jobs`` at a
    time overlapped: each adds its time divided by ``jobs`` (summing them would count the overlap twice)."""
    seconds, missing = 0.0, []
    for entry in ENTRIES:
        if budget.entries is not None and entry.label not in budget.entries:
            continue
        m = measured.get(entry.label) or measured.get(entry.base.label if entry.base else "")
        if m is None or m["batch_size"] != budget.batch_size:
            missing.append(entry.label)
            continue
        per_run = budget.steps * m["ms_per_step"] / 1e3 + m["other_seconds"]
        seconds += per_run / m.get("jobs", 1) * runs_per_seed(entry, budget) * len(budget.seeds)
    return seconds, missing


def projections_text(measured: dict[str, dict[str, float]]) -> str:
    text = ""
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


def header(budget: Budget, mode: str, info: dict) -> str:
    recorded = (
        f" (recorded in this run in {info['record_seconds']:.0f} s)"
        if info["record_seconds"] is not None
        else ""
    )
    return (
        f"# Missing-modality benchmark ({mode} mode)\n\n"
        f"Push dataset {info['data']}: {info['episodes']} episodes{recorded}, "
        "split by episode (split_seed 0), "
        f"{info['test_episodes']} test episodes; images {budget.image_size}x{budget.image_size}, H = T = 10. "
        f"Every model: {budget.steps} steps of batch {budget.batch_size}, "
        f"seeds {', '.join(map(str, budget.seeds))}"
        + ("" if budget.retrained_subsets == "all" else "; retrained baselines only for the paper's subsets")
        + f". Wall time {info['seconds'] / 60:.1f} min"
        + (
            f" for the {info['runs'] - info['reused']} of {info['runs']} runs not reused "
            "from an earlier invocation"
            if info["reused"]
            else ""
        )
        + ".\n\n"
    )


def markdown(
    table: Table,
    collected: Collected,
    budget: Budget,
    mode: str,
    info: dict,
    measured: dict,
    comparisons: dict,
) -> str:
    cv = info["constant_velocity_mse"]
    reference = (
        f"Reference: constant-velocity extrapolation of the object's past position (not a model input), "
        f"MSE {cv:.4f}; predicting the training mean gives about 1.\n\n"
        if cv is not None
        else ""
    )
    intervals = report.episode_intervals_text(info["test_episodes"])
    return (
        header(budget, mode, info)
        + report.results_sections(table, collected, comparisons, push_subset_title, intervals, reference)
        + report.run_time_section(info["cache_seconds"], measured)
        + projections_text(measured)
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
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
    script.add_override_flags(parser, "seeds", "steps", "batch-size")
    parser.add_argument(
        "--entries",
        nargs="+",
        default=None,
        help="override the mode's entries (labels; must include 'paper')",
    )
    script.add_run_flags(parser)
    args = parser.parse_args(argv)
    script.check_run_flags(parser, args, ENTRIES)
    args.mode = next((name for name in ("tiny", "quick", "standard") if getattr(args, name)), "full")
    args.budget = MODES[args.mode].overridden(args)
    args.out = (args.out or REPO / "runs" / f"bench_accuracy_{args.mode}").resolve()
    args.data = (args.data or script.push_recording_path(REPO, args.budget.episodes)).resolve()
    return args


def results_json(
    table: Table, collected: Collected, args, info, episodes, measured, comparisons, summary
) -> dict:
    return {
        "mode": args.mode,
        "budget": args.budget.__dict__,
        "info": info,
        "kinds": collected.kinds,
        "test_episodes": episodes,
        "bootstrap": {"resamples": BOOTSTRAP_RESAMPLES, "seed": BOOTSTRAP_SEED, "level": LEVEL},
        **report.tables_json(table, collected, comparisons, measured),
        "summary": summary,
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    retrained_for = None if args.budget.retrained_subsets == "all" else PAPER_SUBSETS
    study = script.push_study(args, ENTRIES, MODALITIES, retrained_for=retrained_for)
    script.check_study(study, "accuracy benchmark")
    outcome = script.run_study(study, script.PushRecording(args.data, args.budget.episodes))
    collected = outcome.collected
    names = [name for name, _ in subsets(MODALITIES)]
    table, episodes = build_table(
        collected.errors, collected.kinds, names, lead=PAPER_SUBSETS, bases=collected.bases
    )
    line, summary = summarize(table, PAPER_SUBSETS)
    comparisons, measured = paired_comparisons(table), timing(collected.runs)
    info = {
        "data": str(args.data),
        "episodes": script.recorded_episodes(args.data),
        "test_episodes": len(episodes),
        "record_seconds": outcome.record_seconds,
        **outcome.info(),
    }
    text = markdown(table, collected, args.budget, args.mode, info, measured, comparisons) + f"{line}\n"
    results = results_json(table, collected, args, info, episodes, measured, comparisons, summary)
    script.report_results(args.out, text, results)
    return 0


if __name__ == "__main__":
    script.run_as_script(main)
