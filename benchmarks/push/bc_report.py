"""The results page of the push behaviour-cloning experiment (``benchmarks/bc_push.py``): the run's
budget and what its policies read, the recording the forecaster learnt from, the success and loss
tables, the offline errors, the camera-loss target, the forecaster's scale fit and the DAgger rounds.
`benchmarks.push.bc_evaluation` makes the tables; this module words the rest."""

from __future__ import annotations

from benchmarks.push.bc_evaluation import (
    VARIANTS,
    camera_loss,
    camera_target_met,
    figure,
    loss_table,
    success_table,
    validation_table,
)
from benchmarks.push.bc_experiment import Forecaster
from benchmarks.push.outage_evaluation import outage_conditions
from mmf_rl.eval.scale_fit import PatternFit, fit_table, record_method
from mmf_rl.rl.demonstrations import Demonstrations


def results_page(
    args,
    header: str,
    rows: dict,
    errors: dict,
    conditions: list,
    forecaster: Forecaster,
    recorded: Demonstrations,
    dagger_rows: list[dict],
) -> str:
    """The whole page: ``header`` (the run's), its budget and the forecaster's recording, `report`'s
    tables and target, the forecaster's scale fit and the DAgger rounds (``dagger_rows``)."""
    budget = f"{budget_line(args, forecaster, recorded)}\n\n{recording_line(forecaster.trained_on)}"
    extra = calibration_section(forecaster.calibration) + dagger_section(dagger_rows)
    text = report(rows, errors, conditions, args.outage, f"{header}\n\n{budget}", args.privileged_object)
    return text + extra


def budget_line(args, forecaster: Forecaster, recorded: Demonstrations) -> str:
    """The run's budget and what its policies read, for the results page."""
    return (
        f"{args.episodes} episodes per condition, outages {' '.join(args.outage)}, BC seeds {args.bc_seeds}, "
        f"{args.bc_steps} BC steps x {args.bc_batch_size}, {training_outages_phrase(args)}; "
        + ("demonstrations by the steady pusher; " if args.steady_demonstrations else "")
        + (f"latched forecasts (rule {args.latched_forecast}); " if args.latched_forecast else "")
        + (f"action chunks of {args.action_chunk}, temporal ensembling; " if args.action_chunk > 1 else "")
        + (
            f"the `with` policies read the first {args.forecast_steps} forecast steps; "
            if args.forecast_steps
            else ""
        )
        + ("Gaussian-mixture action head (most likely component); " if args.action_head == "gmm" else "")
        + (
            f"policies {' and '.join(args.variants)} forecasts only; "
            if args.variants != list(VARIANTS)
            else ""
        )
        + (
            f"DAgger {args.dagger} rounds of {args.dagger_episodes} episodes per policy; "
            if args.dagger
            else ""
        )
        + (held_out_phrase(forecaster.trained_on) if args.held_out_forecaster else "")
        + ("forecaster trained on the policies' recording (in-sample); " if args.in_sample_forecaster else "")
        + "forecaster "
        f"`{forecaster.checkpoints}`; {len(recorded.split_frames['train'])} recorded training frames"
    )


def training_outages_phrase(args) -> str:
    """The budget line's word on the training outages."""
    if args.train_outages == "replayed":
        played = len(outage_conditions(args.outage))
        return f"training outages replayed through the {played} played conditions x {args.replay_draws} draws"
    return f"training dropout {args.dropout}"


def held_out_phrase(trained_on: dict) -> str:
    """The budget line's word on a held-out forecaster: the seed of its recording when recorded here."""
    own = f"seed {trained_on['seed']}" if trained_on["seed"] is not None else f"`{trained_on['path']}`"
    return f"forecaster trained on its own recording ({own}); "


def recording_line(trained_on: dict) -> str:
    """The results page's line on the recording the forecaster was trained on."""
    seed = "not recorded by this script"
    if trained_on["seed"] is not None:
        seed = f"recorded here with seed {trained_on['seed']}"
    episodes = "episodes unknown" if trained_on["episodes"] is None else f"{trained_on['episodes']} episodes"
    return f"The forecaster was trained on the recording `{trained_on['path']}` ({seed}, {episodes})."


def calibration_section(record: dict | None) -> str:
    """The forecaster's scale calibration: its fit per presence pattern, or that there is none."""
    if record is None:
        return "\nForecast scale: as trained, not calibrated (--no-calibrate).\n"
    if record["split"] is None:
        return f"\nForecast scale: factors {record['factors']} (their fit is not recorded with the model).\n"
    fits = [PatternFit(**fit) for fit in record["patterns"]]
    return (
        f"\nForecast scale: calibrated per presence pattern on the {record['split']} split before any "
        f"forecast (as `mmf-rl calibrate`, method={record_method(record)}, "
        f"min_windows={record['min_windows']}):\n\n"
        f"{fit_table(fits, record['split'])}\n"
    )


def dagger_section(rows: list[dict]) -> str:
    """Per BC seed, round and variant: the policy's success on its own DAgger episodes (those of the
    policy of the round before) and the frames the round's policies are trained on."""
    if not rows:
        return ""
    lines = [
        "| BC seed | round | policy playing | episodes | success % (own episodes) | frames added | "
        "training frames after |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['bc_seed']} | {r['round']} | BC {r['variant']} forecasts of round {r['round'] - 1} | "
            f"{r['episodes']} | {r['success']:.0f} | {r['frames_added']} | {r['frames_trained_on']} |"
        )
    return (
        "\nDAgger (expert: the scripted pusher as a function of the state; every sensor):\n\n"
        + "\n".join(lines)
        + "\n"
    )


def report(rows: dict, errors: dict, conditions: list, outages: list[str], run: str, privileged: bool) -> str:
    """The results page: the run and its budget (``privileged``: the policies were told the object's
    position), the success and loss tables, the offline errors and the camera-loss target."""
    loss = camera_loss(rows, outages)
    met = camera_target_met(loss)
    title = "# Behaviour cloning with and without forecasts on the multimodal push task"
    if privileged:
        title += (
            "\n\nPrivileged policies (a diagnostic, not deployable): every BC policy here also reads the "
            "object's true planar position."
        )
    target = "; ".join(
        f"{outage} {'met' if met[outage] else 'not met'} ({figure(lost[1])} vs {figure(lost[0])} pts)"
        for outage, lost in loss.items()
    )
    if len(errors) < len(VARIANTS):
        target = f"not judged: only the policies {' and '.join(errors)} forecasts were played"
    return (
        f"{title}\n\n{run}\n\n"
        f"{success_table(rows)}\n\nSuccess lost against all sensors:\n\n{loss_table(rows, conditions)}\n\n"
        "Offline: mean squared action error on the validation episodes, with each sensor subset removed "
        f"(mean over BC seeds):\n\n{validation_table(errors)}\n\n"
        f"Camera-loss target (success lost with forecasts <= half of that lost without): {target}\n"
    )
