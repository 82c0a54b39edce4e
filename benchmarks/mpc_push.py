"""MPC with the push world model, robust to sensor outages: success over seeded episodes and
world-model seeds.

    # quick: builds what it lacks (records, trains 2 world models with a small budget), then plays
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --quick
    # full: the committed budget (experiment=world_model), 50 episodes, every outage type
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py
    # given world models (one per training seed), nothing built
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py \
        --checkpoint runs/wm0/checkpoints runs/wm1/checkpoints
    # one agent planning with both world models as an ensemble, penalising their disagreement
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --ensemble --uncertainty-weight 0.1 \
        --checkpoint runs/wm0/checkpoints runs/wm1/checkpoints
    # PETS-style data aggregation: 2 rounds of 100 MPC episodes each, retraining on the union
    MUJOCO_GL=egl .venv/bin/python benchmarks/mpc_push.py --quick --aggregate 2 --aggregate-episodes 100

What it builds when absent (under ``--work``; a re-run reuses the recording and resumes or skips
the trainings): the exploration recording (`mmf_rl.record`, ``--record-episodes`` episodes, seed
1, exploration 0.1, as ``mmf-rl record --out data/push_explore --episodes 300 --seed 1
--exploration 0.1``) and one world model per ``--world-model-seeds`` (``mmf-rl train
experiment=world_model trainer.seed=S``, ``--train-steps`` steps).

=========================  ======  =====
budget                     quick   full
=========================  ======  =====
recorded episodes          300     300
training steps per seed    1500    4000 (configs/experiment/world_model.yaml)
world-model seeds          0 1     0 1
episodes per condition     20      50
outage types               episode episode bursts dies
step-wise CEMPlanner eps.  0       10
aggregation rounds         0       0     (--aggregate; 100 episodes each, --aggregate-episodes)
=========================  ======  =====

Data aggregation (``--aggregate ROUNDS``, PETS-style, `benchmarks.push.aggregation`): after the first
world models are trained, each round records ``--aggregate-episodes`` episodes with the current MPC agent
(`mmf_rl.rl.PushMPCAgent`: the planner and objective below, all sensors up) plus the recorder's
random-move bursts (``--aggregate-exploration``, the meaning of ``mmf-rl record
--exploration``), merges them with that world model's training data (lerobot's
`aggregate_datasets`, `mmf_rl.record.merge_recordings`) and trains the next world model on the
union, with the same seed and step budget, and early stopping on the validation MSE
(``--early-stopping-patience`` evaluations without improvement; the trainer's own
``trainer.early_stopping_patience``, which keeps the weights it stopped with, not the best
evaluation's). The world models of the last round are the ones played.
Each world-model seed aggregates its own data (its agent records, its union trains it): the seeds
stay independent replicates of the whole procedure, so their spread includes the data's. A
retraining starts from scratch by default: the union's normalisation statistics differ from
the last round's, and a model trained by the same recipe on more data is what the rounds are
meant to measure; ``--aggregate-warm-start`` starts from the last round's weights instead
(``init_from``: new optimizer and schedule, the union's statistics), which converges in fewer
steps with early stopping. Round ``r`` records with seed ``r + 1`` (the first recording's is 1),
so its episodes start elsewhere, with the first recording's image size and episode length.
``results.md`` lists every round: episodes recorded, episodes
trained on, the recording agent's success (the object within FetchPush's 5 cm of the goal at
some recorded frame, exploration bursts included) and the steps trained.

Run time: the script prints the minutes of each phase (record, each training, play) and the
total, and writes them to ``results.md``; the quick mode is sized to finish within 25 min on 2
CPU cores (the measured times of both modes are in docs/results.md).

Every policy plays the same seeded episodes of `MultimodalPushTorchEnv` (episode ``i`` is reset
with seed ``seed + i``; success is FetchPush's: the object within 5 cm of the goal, within the
50-step time limit). The outages are seeded too: every world model meets the same ones.

* ``mpc all`` / ``mpc no-camera (<outage>)`` / ``mpc no-force (<outage>)``: `SequenceCEMPlanner`
  on the world model with `PushObjective`, the camera or the force sensor failing the
  ``--outage`` way (`ModalityDropout`): ``episode``: off for the whole episode; ``bursts``:
  outages of 2-8 steps starting with probability 0.2 at each step it is up (absent about half
  the time); ``dies``: works for 1-49 steps (uniform), then is off until the episode ends. The
  same world model plans from the remaining sensors: no retraining per outage.
* ``mpc static model``: the same planner and objective with a "world model" that forecasts no
  object motion (all sensors): what the objective's kinematic approach term achieves alone.
* ``scripted``: the pusher that recorded the training data (`ScriptedPusher`, without
  exploration), a strong hand-written controller with full state;
* ``random``: uniform random actions.

The order of the MPC conditions can flip from one world-model training to the next, so
every MPC row is given per world-model seed and as mean with its spread (min-max) over seeds,
beside the median decision time per step (the planner's call, measured in the same run).

Uncertainty penalty (``--uncertainty-weight W``, default 0): every planner above (and the
aggregation's recording agent) scores a plan with ``PushObjective(uncertainty_weight=W)``, which
takes from each forecast step's reward ``W`` times the norm of the world model's predictive
standard deviation of the object's position (metres; the decoder's scale, calibrated when the
checkpoint was): among plans forecast to push equally well it prefers the one the model is sure
of, against pushes whose outcome it cannot tell (the block slipping sideways on a long push).
The push world model's scale is the outcome's own noise, largest for the plans that touch the
object, so on push any weight that matters keeps the planner from pushing (docs/results.md).
At 0 the planner never asks for the scale and plans exactly as without the option. The results
page records the weight beside the CEM sizes; the summary line is the same.

Ensemble (``--ensemble``, PETS-style): instead of one MPC agent per world model, one agent plans
with all of them (``--checkpoint`` or built) as an `mmf_rl.rl.EnsembleWorldModel`: the members'
mean forecast, and as its scale their disagreement (the std over members of their forecasts),
which is epistemic (largest where the data left the outcome open) where the decoder's scale is
the outcome's own noise. ``--uncertainty-weight`` then penalises the disagreement. The ensemble
counts as one world-model seed in the rows (spread and per-seed cells show that one agent), the
static model plays on its first member, the step-wise `CEMPlanner` rolls out the ensemble too
(its rows say "the ensemble" for "world model 1"), and aggregation rounds still record with each
seed's own agent. The results page names the ensemble's checkpoints.

Step-wise vs vectorised planning: the first
``--stepwise-episodes`` episodes are also played with torchrl's `CEMPlanner` rolling out
`ForecasterWorldModelEnv` step by step with the first world model (or the ensemble), with the
same candidates, iterations and elites.

Ends with ``summary: success all A%, no-camera B%, no-force C%, scripted S%, random R%`` (MPC:
mean over world-model seeds, or the ensemble's; the first ``--outage`` type).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

# Run as `python benchmarks/X.py` or by `mmf-rl bench`: the checkout is what makes `benchmarks` importable.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.push.aggregation import (
    FIRST_RECORDING,
    SUCCESS_DISTANCE,
    AggregationConfig,
    add_aggregation_arguments,
    aggregate_data,
    aggregation_table,
    check_aggregation_arguments,
    train_world_model,
)
from benchmarks.push.closed_loop import OUTAGES
from benchmarks.push.experiment import (
    add_common_arguments,
    resolve_budget,
    run_header,
    timed_phase,
    write_results,
)
from benchmarks.push.mpc_evaluation import evaluate_mpc, results_table
from benchmarks.push.outage_evaluation import outage_conditions
from mmf_rl.log import configure_logging
from mmf_rl.record import RecordConfig, record
from mmf_rl.rl import PushMPCAgent, PushObjective

BUDGETS = {
    "quick": {
        "record_episodes": 300,
        "train_steps": 1500,
        "episodes": 20,
        "outage": ["episode"],
        "stepwise_episodes": 0,
    },
    "full": {
        "record_episodes": 300,
        "train_steps": None,
        "episodes": 50,
        "outage": list(OUTAGES),
        "stepwise_episodes": 10,
    },
}


def training_overrides(args) -> list[str]:
    """What every world-model training adds to ``experiment=world_model``."""
    steps = [] if args.train_steps is None else [f"trainer.total_steps={args.train_steps}"]
    return [*args.train_override, *steps]


def build_world_models(args, phases: dict[str, float]) -> list[Path]:
    """The recording and one world model per seed under ``args.work``, built where absent."""
    data = args.work / "push_explore"
    if not (data / "meta" / "info.json").is_file():
        print(f"mpc_push: recording {args.record_episodes} exploration episodes into {data}")
        with timed_phase(phases, "record"):
            record(
                RecordConfig(out=data, episodes=args.record_episodes, workers=args.workers, **FIRST_RECORDING)
            )
    checkpoints = []
    for seed in args.world_model_seeds:
        with timed_phase(phases, f"train seed {seed}"):
            run_dir = args.work / f"world_model_seed{seed}"
            checkpoints.append(train_world_model(run_dir, data, seed, training_overrides(args)))
    return checkpoints


def aggregation_config(args) -> AggregationConfig:
    return AggregationConfig(
        work=args.work,
        seeds=args.world_model_seeds,
        rounds=args.aggregate,
        episodes=args.aggregate_episodes,
        exploration=args.aggregate_exploration,
        early_stopping_patience=args.early_stopping_patience,
        warm_start=args.aggregate_warm_start,
        workers=args.workers,
        agent={
            "num_candidates": args.candidates,
            "num_iterations": args.iterations,
            "num_elites": args.elites,
            "reach_weight": args.reach_weight,
            "uncertainty_weight": args.uncertainty_weight,
            "keep_out_weight": args.keep_out_weight,
        },
        train_overrides=training_overrides(args),
    )


def add_world_model_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--checkpoint",
        type=Path,
        nargs="+",
        default=None,
        help="world models to use, one per training seed (default: build them under --work)",
    )
    parser.add_argument(
        "--world-model-seeds", type=int, nargs="+", default=[0, 1], help="trainer.seed of each"
    )
    parser.add_argument(
        "--ensemble",
        action="store_true",
        help="one MPC agent planning with all world models as an ensemble (their disagreement is the "
        "scale --uncertainty-weight penalises), instead of one agent per world model",
    )
    parser.add_argument(
        "--train-steps", type=int, default=None, help="default: quick 1500, full the config's"
    )
    parser.add_argument(
        "--train-override",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="Hydra overrides added to every world-model training (e.g. model.d_model=64)",
    )


def add_planner_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--stepwise-episodes",
        type=int,
        default=None,
        help="episodes also played with torchrl's CEMPlanner (0: skip; quick 0, full 10)",
    )
    parser.add_argument("--candidates", type=int, default=PushMPCAgent.num_candidates)
    parser.add_argument("--iterations", type=int, default=PushMPCAgent.num_iterations)
    parser.add_argument("--elites", type=int, default=PushMPCAgent.num_elites)
    parser.add_argument("--reach-weight", type=float, default=PushMPCAgent.reach_weight)
    parser.add_argument(
        "--keep-out-weight",
        type=float,
        default=PushMPCAgent.keep_out_weight,
        help="PushObjective's keep_out_weight: metres of goal distance per metre the approaching gripper "
        "is below travel height near the block (0: no term)",
    )
    parser.add_argument(
        "--uncertainty-weight",
        type=float,
        default=PushMPCAgent.uncertainty_weight,
        help="PushObjective's uncertainty_weight: metres of goal distance per metre of the forecast's "
        "std (0: no penalty, the planner as without it)",
    )


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(parser, "mpc")
    add_world_model_arguments(parser)
    add_planner_arguments(parser)
    add_aggregation_arguments(parser)
    args = parser.parse_args()
    check_aggregation_arguments(parser, args, world_models_given=bool(args.checkpoint))
    if args.ensemble and len(args.checkpoint or args.world_model_seeds) < 2:
        parser.error("--ensemble needs 2 world models at least (--checkpoint A B or --world-model-seeds 0 1)")
    try:  # the objective checks its weights: built here, a bad flag fails before any recording
        args.objective = PushObjective(
            reach_weight=args.reach_weight,
            uncertainty_weight=args.uncertainty_weight,
            keep_out_weight=args.keep_out_weight,
        )
    except ValueError as error:
        parser.error(str(error))
    return resolve_budget(args, BUDGETS, "mpc")


def main() -> None:
    args = parse_args()
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    phases: dict[str, float] = {}
    checkpoints = args.checkpoint or build_world_models(args, phases)
    aggregation: list[dict] = []
    if args.aggregate:
        checkpoints, aggregation = aggregate_data(aggregation_config(args), checkpoints, phases)

    conditions = outage_conditions(args.outage)
    sizes = {"num_candidates": args.candidates, "num_iterations": args.iterations, "num_elites": args.elites}
    with timed_phase(phases, "play"):
        rows, raw = evaluate_mpc(
            checkpoints,
            args.objective,
            conditions,
            sizes,
            args.episodes,
            args.seed,
            args.stepwise_episodes,
            ensemble=args.ensemble,
        )

    text = report(
        args,
        rows,
        aggregation,
        checkpoints,
        run_header("benchmarks/mpc_push.py", sys.argv[1:], started, phases),
    )
    write_results(args, text, {"rows": rows, "aggregation": aggregation, "episodes": raw}, phases)
    print(text)
    labels = [condition.label for condition in conditions]
    spread = ", ".join(
        f"{label} {rows[f'mpc {label}']['success_min']:.0f}-{rows[f'mpc {label}']['success_max']:.0f}%"
        for label in labels
    )
    decision = statistics.median(rows[f"mpc {label}"]["decision_ms"] for label in labels)
    seeds = args.world_model_seeds if not args.checkpoint else len(checkpoints)
    print(
        "spread over world-model seeds "
        f"{f'1 (the ensemble of {len(checkpoints)})' if args.ensemble else seeds}: "
        f"{spread}; MPC decision {decision:.1f} ms/step (median)"
    )
    first = args.outage[0]
    print(
        f"summary: success all {rows['mpc all']['success']:.0f}%, "
        f"no-camera {rows[f'mpc no-camera ({first})']['success']:.0f}%, "
        f"no-force {rows[f'mpc no-force ({first})']['success']:.0f}%, scripted "
        f"{rows['scripted']['success']:.0f}%, "
        f"random {rows['random']['success']:.0f}%"
    )


def report(args, rows: dict, aggregation: list[dict], checkpoints: list[Path], header: str) -> str:
    """The results page: the run, its budget, the table, and the aggregation rounds if any."""
    built = (
        ""
        if args.checkpoint
        else f" (seeds {args.world_model_seeds}, {args.train_steps or 'the config'} training steps, "
        f"{args.record_episodes} recorded episodes)"
    )
    aggregated = (
        f"; {args.aggregate} aggregation rounds of {args.aggregate_episodes} MPC episodes "
        f"(exploration {args.aggregate_exploration}, "
        f"{'warm start' if args.aggregate_warm_start else 'retrained from scratch'}, "
        f"early stopping patience {args.early_stopping_patience})"
        if args.aggregate
        else ""
    )
    budget = (
        f"{args.episodes} episodes per condition, outages {' '.join(args.outage)}, "
        f"{len(checkpoints)} world models{built}{aggregated}"
    )
    planned = (
        " (planned with as one ensemble: one MPC agent, its uncertainty the members' disagreement)"
        if args.ensemble
        else ""
    )
    text = (
        f"# MPC on the multimodal push task\n\n{header}\n\n{budget}; world models: "
        f"{', '.join(f'`{c}`' for c in checkpoints)}{planned}; CEM {args.candidates} candidates × "
        f"{args.iterations} iterations, {args.elites} elites; objective: reach weight {args.reach_weight}, "
        f"uncertainty weight {args.uncertainty_weight}, keep-out weight {args.keep_out_weight}\n\n"
        f"{results_table(rows)}\n"
    )
    if aggregation:
        text += (
            "\n## Data aggregation\n\nRound r records with the MPC agent of round r - 1's world model "
            "(all sensors, plus exploration bursts), and trains round r's world model on the union; "
            "the last round's world models are the ones played above. Recording success: the object "
            f"within {100 * SUCCESS_DISTANCE:.0f} cm of the goal at some recorded frame.\n\n"
            f"{aggregation_table(aggregation)}\n"
        )
    return text


if __name__ == "__main__":
    configure_logging()  # the library's progress messages, as `mmf-rl bench` shows them
    main()
