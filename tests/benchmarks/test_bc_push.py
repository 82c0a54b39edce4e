"""benchmarks/bc_push.py end to end with tiny budgets, run as a user runs it (``mmf-rl bench bc``, in
this process: a subprocess would add its imports to the test's time): builds the forecaster and
both policies, plays, writes the results and ends with the summary line.

Every episode played ends after `TEST_EPISODE_STEPS` steps (`short_push_episodes`). The plain run is
played once for the module (`plain_run`); a test of an option whose runs are its own runs it in a copy
of that work directory, where the forecaster it would train is there already, and checks that the
plain run's files are left as they were (`assert_plain_run_left_alone`)."""

from __future__ import annotations

import contextlib
import fnmatch
import io
import json
import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from benchmarks.bc_push import parse_args
from benchmarks.push.bc_experiment import (
    FORECASTER_RECORD,
    Forecaster,
    build_recording,
    forecaster_run_dir,
    policy_run_dir,
    record_or_check_forecaster,
    warn_of_in_sample_forecasts,
)
from benchmarks.push.gmm_head import GMMPolicy
from mmf_rl.checkpoint import list_checkpoints
from mmf_rl.cli import main as cli
from mmf_rl.datasets.provenance import PROVENANCE_FILE, read_recording_provenance
from mmf_rl.rl import BCPolicy
from tests.benchmarks.conftest import TEST_EPISODE_STEPS, short_push_episodes
from tests.conftest import TEST_THREADS, push_train_overrides


def assert_one_outage_summary(out: str) -> None:
    """The run's last stdout line (of ``out``) is bc_push's summary line for one outage type
    (``--outage episode``)."""
    last = out.strip().splitlines()[-1]
    pct = r"\d+%/\d+%"
    assert re.fullmatch(
        rf"summary: BC success all {pct}, no-camera {pct}, no-force {pct} \(without/with forecasts\); "
        r"camera loss without/with forecasts episode -?\d+/-?\d+ pts "
        r"\(target with <= without/2: met for [01] of 1 outage types\)",
        last,
    ), last


@pytest.fixture(scope="module")
def plain_run(recorded_push_root, push_cache_dir, tmp_path_factory) -> tuple[Path, str]:
    """`tiny_argv`'s plain run without DAgger, played once for the module: its --work directory and its
    stdout. Read by the tests of what a run builds; a test that runs more in that work copies it first
    (`copied_work`)."""
    work = tmp_path_factory.mktemp("bc_push_plain") / "work"
    out = io.StringIO()
    with pytest.MonkeyPatch.context() as patch, contextlib.redirect_stdout(out):
        short_push_episodes(patch)
        assert cli(tiny_argv(recorded_push_root, push_cache_dir, work, dagger=False)) == 0
    return work, out.getvalue()


def copied_work(plain_run, tmp_path) -> Path:
    """A copy of the plain run's --work directory (modification times kept) in ``tmp_path``. Its
    forecaster moved with it: the ``with`` runs' record of their forecaster says so, as a refusal to
    reuse them asks (`record_or_check_forecaster`), its modification time kept too."""
    work = Path(shutil.copytree(plain_run[0], tmp_path / "work"))
    for record in work.glob(f"*/{FORECASTER_RECORD}"):
        times = record.stat()
        moved = json.loads(record.read_text())["checkpoints"].replace(str(plain_run[0]), str(work))
        record.write_text(json.dumps({"checkpoints": moved}))
        os.utime(record, ns=(times.st_atime_ns, times.st_mtime_ns))
    return work


def made_in(work: Path, plain_run) -> list[str]:
    """The names of what a run in ``work``, a `copied_work` of the plain run, made at its top level."""
    return sorted({p.name for p in work.iterdir()} - {p.name for p in plain_run[0].iterdir()})


def assert_plain_run_left_alone(work: Path, plain_run, but: tuple[str, ...] = ()) -> None:
    """Every file of the plain run (its forecaster, policies and results) in ``work``, a `copied_work`
    of it, is as the copy left it (its modification time), but those under the top-level names ``but``."""
    plain = plain_run[0]
    files = [p.relative_to(plain) for p in plain.rglob("*") if p.is_file()]
    assert files
    for path in files:
        if path.parts[0] not in but:
            assert (work / path).stat().st_mtime_ns == (plain / path).stat().st_mtime_ns, path


def assert_built_what_it_lacked(work: Path, out: str, latched: str | None) -> None:
    """A run without DAgger (``--latched-forecast latched``) in the empty ``work`` built the forecaster and
    both policies, played every condition, wrote the results and ended with the summary line."""
    assert_one_outage_summary(out)
    results = json.loads((work / "results.json").read_text())
    conditions = ["all", "no-camera (episode)", "no-force (episode)"]
    expected = {f"BC {v} forecasts | {c}" for v in ("without", "with") for c in conditions} | {
        "scripted | all"
    }
    assert set(results["rows"]) == expected
    assert set(results["validation_errors"]) == {"without", "with"}
    assert results["action_chunk"] == 1 and results["action_head"] == "mse"
    with_run = f"bc_with_latched_{latched}_forecasts_seed0" if latched else "bc_with_forecasts_seed0"
    for run in ("bc_without_forecasts_seed0", with_run):
        assert (work / run / "checkpoints" / "last").is_file()
    assert BCPolicy.from_checkpoint(work / with_run / "checkpoints").config.latched_forecast == latched


def test_bc_push_builds_what_it_lacks_and_ends_with_the_summary(plain_run):
    assert_built_what_it_lacked(*plain_run, latched=None)


def test_bc_push_with_a_latched_forecast_builds_what_it_lacks_and_ends_with_the_summary(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # the forecaster and the policy without forecasts are there
    argv = tiny_argv(recorded_push_root, push_cache_dir, work, dagger=False)
    assert cli([*argv, "--latched-forecast", "precision"]) == 0
    assert_built_what_it_lacked(work, capsys.readouterr().out, latched="precision")
    assert made_in(work, plain_run) == ["bc_with_latched_precision_forecasts_seed0"]
    # The latched with policy's run is its own; the results of a run without DAgger go to WORK.
    assert_plain_run_left_alone(work, plain_run, but=("results.json", "results.md"))


# The plain policies: a style drawn per episode, one action per step, the forecast of the live sensors
# relative to the gripper, from whole windows.
PLAIN = [
    "--demonstrations",
    "drawn",
    "--action-chunk",
    "1",
    "--latched-forecast",
    "none",
    "--forecast-target",
    "gripper",
]


def tiny_argv(
    recorded_push_root, cache_dir, work, *, forecaster: str | Path = "in-sample", data=True, dagger=True
) -> list[str]:
    """`mmf-rl bench bc` at sizes that run in seconds. ``forecaster``: ``"in-sample"``, trained on the
    policies' recording; ``"held-out"``, the default, trained on a recording the script makes; or the
    checkpoints of one trained already (``--forecaster``). The forecaster's data root and run directory
    are the test's only in-sample with ``--data``; otherwise the script's. ``data=False``: no
    ``--data``, the script records 4 episodes for the policies; ``dagger``: one DAgger round. The
    policies are the plain ones (`PLAIN`), not the script's defaults, which tests below cover."""
    overrides = push_train_overrides(recorded_push_root, cache_dir, work / "forecaster", steps=3)
    if forecaster != "in-sample" or not data:
        overrides = [o for o in overrides if not o.startswith(("data.root=", "run_dir="))]
    kind = {"in-sample": ["--in-sample-forecaster"], "held-out": []}
    records = forecaster == "held-out" or not data
    return [
        *("bench", "bc", "--quick", "--work", str(work)),
        *(("--data", str(recorded_push_root)) if data else ("--record-episodes", "4")),
        *("--forecaster-override", *overrides),
        *("--bc-steps", "3", "--bc-batch-size", "16", "--bc-seeds", "0"),
        *("--bc-d-model", "8", "--bc-hidden", "16", "--bc-image-channels", "8", "16"),
        *("--episodes", "1", "--outage", "episode"),
        *kind.get(forecaster, ["--forecaster", str(forecaster)]),
        *(("--dagger", "1", "--dagger-episodes", "1") if dagger else ()),
        *(("--workers", "1") if records else ()),
        # The suite's threads (1 in an xdist worker), not the script's 2: OpenMP threads spin-wait
        # for a busy core, so 2 beside the other worker run far slower than 1.
        *("--threads", str(TEST_THREADS)),
        *PLAIN[2:],
        *(PLAIN[:2] if not data else ()),
    ]


def test_bc_push_dagger_adds_labelled_episodes_and_a_rerun_reuses_every_round(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # round 0: the plain run's policies
    argv = tiny_argv(recorded_push_root, push_cache_dir, work)
    assert cli(argv) == 0
    assert_plain_run_left_alone(work, plain_run)  # round 0's policies and results are not written over
    assert made_in(work, plain_run) == ["dagger1", "dagger_markov_seed0_round1"]
    first = json.loads((work / "dagger1" / "results.json").read_text())
    rows = first["dagger"]
    assert [(r["bc_seed"], r["round"], r["variant"], r["episodes"]) for r in rows] == [
        (0, 1, "without", 1),
        (0, 1, "with", 1),
    ]
    recorded_frames = rows[0]["frames_trained_on"] - sum(r["frames_added"] for r in rows)
    assert recorded_frames > 0 and all(0 < r["frames_added"] <= TEST_EPISODE_STEPS for r in rows)
    assert first["forecaster_calibration"]["split"] == "val"  # mmf-rl train fitted it
    round_dir = work / "dagger_markov_seed0_round1"
    for variant in ("without", "with"):
        assert (round_dir / f"bc_{variant}_forecasts" / "checkpoints" / "last").is_file()
    page = (work / "dagger1" / "results.md").read_text()
    assert "DAgger (expert: the scripted pusher" in page
    assert "Forecast scale: calibrated per presence pattern on the val split" in page

    # A re-run trains and plays nothing it already has (the forecaster: `train_or_resume` leaves an
    # ended run as it is): only the test episodes are played.
    capsys.readouterr()
    assert cli(argv) == 0
    again = json.loads((work / "dagger1" / "results.json").read_text())
    assert again["dagger"] == rows
    assert not [p for p in again["phases_s"] if p.startswith(("train BC", "DAgger"))], again["phases_s"]


def test_bc_push_privileged_object_trains_only_the_variant_asked_in_runs_of_its_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # its forecaster is there
    argv = [
        *tiny_argv(recorded_push_root, push_cache_dir, work),
        "--privileged-object",
        "--variants",
        "without",
    ]
    assert cli(argv) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.fullmatch(
        r"summary: BC success all \d+%/-, no-camera \d+%/-, no-force \d+%/- \(without/with forecasts\); "
        r"camera loss without/with forecasts episode -?\d+/- pts "
        r"\(target with <= without/2: met for 0 of 1 outage types\)",
        last,
    ), last
    assert_plain_run_left_alone(work, plain_run)  # the ordinary policies and their results
    results = json.loads((work / "privileged_dagger1" / "results.json").read_text())
    assert {r for r in results["rows"] if r.startswith("BC")} == {
        f"BC without forecasts | {c}" for c in ("all", "no-camera (episode)", "no-force (episode)")
    }
    assert [(r["round"], r["variant"]) for r in results["dagger"]] == [(1, "without")]
    page = (work / "privileged_dagger1" / "results.md").read_text()
    assert "Privileged policies" in page and "not judged" in page
    for run in (
        "bc_privileged_without_forecasts_seed0",
        "dagger_markov_privileged_without_seed0_round1/bc_without_forecasts",
    ):
        assert BCPolicy.from_checkpoint(work / run / "checkpoints").config.privileged_object
    made = made_in(work, plain_run)
    assert not fnmatch.filter(made, "bc_with*") and not fnmatch.filter(made, "bc_without*"), made


def test_bc_push_action_chunks_reach_every_policy_in_runs_of_their_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # its forecaster is there
    assert cli([*tiny_argv(recorded_push_root, push_cache_dir, work), "--action-chunk", "2"]) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    assert_plain_run_left_alone(work, plain_run)  # the per-step policies and their results
    assert json.loads((work / "chunk2_dagger1" / "results.json").read_text())["action_chunk"] == 2
    for run in (
        "bc_chunk2_without_forecasts_seed0",
        "bc_chunk2_with_forecasts_seed0",
        "dagger_markov_chunk2_seed0_round1/bc_without_forecasts",
        "dagger_markov_chunk2_seed0_round1/bc_with_forecasts",
    ):
        assert BCPolicy.from_checkpoint(work / run / "checkpoints").config.action_chunk == 2, run
    made = made_in(work, plain_run)
    assert not fnmatch.filter(made, "bc_with*") and not fnmatch.filter(made, "bc_without*"), made
    assert not (work / "dagger_markov_seed0_round1").exists()


def test_bc_push_gmm_head_reaches_every_policy_in_runs_of_their_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # its forecaster is there
    argv = tiny_argv(recorded_push_root, push_cache_dir, work, dagger=False)
    assert cli([*argv, "--action-head", "gmm", "--action-chunk", "2"]) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    assert_plain_run_left_alone(work, plain_run)  # the regression policies and their results
    results = json.loads((work / "chunk2_gmm" / "results.json").read_text())
    assert results["action_head"] == "gmm" and results["action_chunk"] == 2
    for run in ("bc_chunk2_gmm_without_forecasts_seed0", "bc_chunk2_gmm_with_forecasts_seed0"):
        config = GMMPolicy.from_checkpoint(work / run / "checkpoints").config
        assert config.action_chunk == 2, run
    made = made_in(work, plain_run)
    assert not fnmatch.filter(made, "bc_with*") and not fnmatch.filter(made, "bc_without*"), made
    assert not fnmatch.filter(made, "bc_chunk2_with*") and not fnmatch.filter(made, "bc_chunk2_without*")


def test_bc_push_replayed_outages_train_both_variants_in_runs_of_their_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # its forecaster is there
    argv = tiny_argv(recorded_push_root, push_cache_dir, work, dagger=False)
    replayed = [*argv, "--train-outages", "replayed", "--latched-forecast", "precision"]
    assert cli([*replayed, "--replay-draws", "1"]) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    assert_plain_run_left_alone(work, plain_run)  # the independently trained policies and their results
    results = json.loads((work / "replayed" / "results.json").read_text())
    assert results["train_outages"] == "replayed" and "replay the training outages" in results["phases_s"]
    fractions = results["replayed_absent_fraction"]
    assert fractions["all"] == {"image": 0.0, "force": 0.0, "proprio": 0.0}
    assert (
        fractions["no-camera (episode)"]["image"] == 1.0 and fractions["no-force (episode)"]["force"] == 1.0
    )
    for run in ("bc_replayed_without_forecasts_seed0", "bc_replayed_with_latched_precision_forecasts_seed0"):
        meta = json.loads((list_checkpoints(work / run / "checkpoints")[-1] / "meta.json").read_text())
        assert meta["replayed_outages"] == ["all", "no-camera (episode)", "no-force (episode)"], run
    made = made_in(work, plain_run)
    assert not fnmatch.filter(made, "bc_with*") and not fnmatch.filter(made, "bc_without*"), made
    assert cli([*replayed, "--replay-draws", "1"]) == 0  # the policies are reused: nothing is replayed
    again = json.loads((work / "replayed" / "results.json").read_text())
    assert (
        again["replayed_absent_fraction"] is None and "replay the training outages" not in again["phases_s"]
    )
    capsys.readouterr()
    assert cli([*replayed, "--replay-draws", "2"]) == 1  # other replays than the policies' own
    assert "trained on the outages replayed through" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        parse_args([*argv, "--train-outages", "replayed", "--dagger", "1"])


def test_bc_push_forecast_steps_reach_only_the_with_policies_in_runs_of_their_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # the forecaster and the policy without forecasts are there
    argv = tiny_argv(recorded_push_root, push_cache_dir, work, dagger=False)
    assert cli([*argv, "--forecast-steps", "1"]) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    # The policies reading every step of the forecast and their results are left alone.
    assert_plain_run_left_alone(work, plain_run)
    assert made_in(work, plain_run) == ["bc_with_first1_forecasts_seed0", "first1"]
    assert json.loads((work / "first1" / "results.json").read_text())["forecast_steps"] == 1
    read = {
        run: BCPolicy.from_checkpoint(work / run / "checkpoints").config.forecast_steps
        for run in ("bc_with_first1_forecasts_seed0", "bc_without_forecasts_seed0")
    }
    assert read == {"bc_with_first1_forecasts_seed0": 1, "bc_without_forecasts_seed0": None}


def first_goal(root) -> np.ndarray:
    """The goal of the first frame of episode 0 of the recording at ``root``."""
    frames = pd.concat(pd.read_parquet(p) for p in sorted((root / "data").glob("*/*.parquet")))
    return np.asarray(frames[frames["episode_index"] == 0]["observation.goal"].iloc[0])


def test_bc_push_held_out_forecaster_learns_from_a_recording_of_its_own_in_runs_of_their_own(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    from mmf_rl.envs.push import MultimodalPushEnv
    from mmf_rl.envs.scripted import episode_generator, reset_for_push

    work = copied_work(plain_run, tmp_path)  # the ordinary (in-sample) policies, trained
    without = work / "bc_without_forecasts_seed0" / "checkpoints"
    trained = {p: p.stat().st_mtime_ns for p in without.rglob("*")}
    in_sample_with = work / "bc_with_forecasts_seed0"
    trained_with = {p: p.stat().st_mtime_ns for p in in_sample_with.rglob("*")}
    assert trained and trained_with, "the plain run trained both policies: what must be left alone"
    ordinary_results = (work / "results.json").read_text()

    assert cli(tiny_argv(recorded_push_root, push_cache_dir, work, forecaster="held-out")) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    recording = work / "push_forecaster"
    info = json.loads((recording / "meta" / "info.json").read_text())
    source = json.loads((recorded_push_root / "meta" / "info.json").read_text())
    for key in ("total_episodes", "total_frames"):
        assert info[key] == source[key], key
    env = MultimodalPushEnv(image_size=32)
    try:
        seed_one_goal = reset_for_push(env, episode_generator(1, 0))[0]["desired_goal"]
    finally:
        env.close()
    np.testing.assert_allclose(first_goal(recording), seed_one_goal, atol=1e-6)
    assert not np.allclose(first_goal(recording), first_goal(recorded_push_root))
    config = yaml.safe_load((work / "forecaster_held_out" / "config.yaml").read_text())
    assert config["data"]["root"] == str(recording.resolve())
    target = config["data"]["target"]
    assert not target["relative"], "the object's position relative to the gripper, not its displacement"
    assert target["relative_to"] == {"feature": "observation.state", "dims": [0, 1]}

    assert (work / "results.json").read_text() == ordinary_results, "the ordinary results are left alone"
    results = json.loads((work / "heldout_dagger1" / "results.json").read_text())
    assert results["held_out_forecaster"]
    assert results["forecaster_recording"] == {
        "path": str(recording.resolve()),
        "seed": 1,
        "episodes": source["total_episodes"],
    }
    page = (work / "heldout_dagger1" / "results.md").read_text()
    assert "forecaster trained on its own recording (seed 1)" in page
    assert f"trained on the recording `{recording.resolve()}` (recorded here with seed 1" in page
    for run in ("bc_with_heldout_forecasts_seed0", "dagger_markov_heldout_seed0_round1/bc_with_forecasts"):
        assert (work / run / "checkpoints" / "last").is_file(), run
    assert {p: p.stat().st_mtime_ns for p in in_sample_with.rglob("*")} == trained_with
    assert "train BC without seed 0" not in results["phases_s"], "the ordinary without policy is reused"
    assert {p: p.stat().st_mtime_ns for p in without.rglob("*")} == trained


def test_bc_push_steady_demonstrations_are_recorded_by_the_steady_pusher_in_runs_of_their_own(
    recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    from mmf_rl.envs.push import MultimodalPushEnv
    from mmf_rl.envs.scripted import rollout

    work = tmp_path / "work"
    argv = tiny_argv(recorded_push_root, push_cache_dir, work, data=False, dagger=False)
    assert cli([*argv, "--steady-demonstrations", "--variants", "without"]) == 0
    parquets = sorted((work / "push_steady" / "data").glob("*/*.parquet"))
    frames = pd.concat(pd.read_parquet(p) for p in parquets)
    env = MultimodalPushEnv(image_size=64)
    try:
        steady = rollout(env, seed=0, episode_index=0, steps=50, steady=True)
    finally:
        env.close()
    actions = np.stack(frames[frames["episode_index"] == 0]["action"])
    np.testing.assert_allclose(actions, steady["action"], atol=1e-6)
    assert not (work / "push").exists() and not (work / "results.json").exists()
    results = json.loads((work / "steady" / "results.json").read_text())
    recording = (work / "push_steady").resolve()
    assert results["policies_recording"] == {
        "path": str(recording),
        "provenance": read_recording_provenance(recording),
    }
    assert results["policies_recording"]["provenance"]["steady"] is True
    assert "demonstrations by the steady pusher" in (work / "steady" / "results.md").read_text()
    assert "train BC without seed 0" in results["phases_s"]
    assert (work / "bc_steady_without_forecasts_seed0" / "checkpoints" / "last").is_file()
    with pytest.raises(SystemExit):
        parse_args(["--work", str(work), "--steady-demonstrations", "--data", str(recorded_push_root)])
    assert "--demonstrations steady records the policies' recording, but --data" in capsys.readouterr().err


def test_bc_push_refuses_a_reused_recording_of_another_kind_and_warns_when_it_cannot_tell(
    recorded_push_root, tmp_path, caplog
):
    work = tmp_path / "work"
    found = Path(shutil.copytree(recorded_push_root, work / "push_steady"))  # a drawn recording, seed 3
    episodes = read_recording_provenance(found)["episodes"]
    argv = ["--quick", "--work", str(work), "--record-episodes", str(episodes)]  # steady demonstrations
    args, phases = parse_args(argv), {}
    with pytest.raises(ValueError) as refused:
        build_recording(args, phases)
    message = str(refused.value)
    assert message.startswith(f"{found.resolve() / PROVENANCE_FILE}: recorded by mmf-rl record: ")
    assert "seed 3, scripted pusher, a style drawn per episode" in message
    assert (
        "expects demonstrations by the scripted pusher (steady) with seed 0" in message
        and "another --work" in message
    )

    steady = {**read_recording_provenance(found), "steady": True, "seed": 0}
    (found / PROVENANCE_FILE).write_text(json.dumps(steady))
    assert build_recording(args, phases) == found.resolve() and not phases, "reused, nothing recorded"
    with pytest.raises(ValueError, match=f"holds {episodes} episodes, this run's budget is 200") as refused:
        build_recording(parse_args(["--quick", "--work", str(work)]), phases)  # a quick run's budget
    assert f"give --record-episodes {episodes} to use it as it is" in str(refused.value)

    (found / PROVENANCE_FILE).unlink()  # a recording made before recordings kept their provenance
    with caplog.at_level(logging.WARNING, logger="mmf_rl"):
        assert build_recording(args, phases) == found.resolve() and not phases
    assert [r.getMessage() for r in caplog.records] == [
        f"{found.resolve()} has no {PROVENANCE_FILE}: reused, but whether it holds demonstrations by the "
        "scripted pusher (steady) with seed 0 cannot be checked"
    ]


def test_bc_push_in_sample_forecaster_learns_from_the_policies_recording_in_untagged_runs(
    recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = tmp_path / "work"
    assert cli(tiny_argv(recorded_push_root, push_cache_dir, work, data=False, dagger=False)) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    recording = (work / "push").resolve()
    config = yaml.safe_load((work / "forecaster" / "config.yaml").read_text())
    assert config["data"]["root"] == str(recording)
    results = json.loads((work / "results.json").read_text())
    assert not results["held_out_forecaster"]
    assert results["forecaster_recording"] == {"path": str(recording), "seed": 0, "episodes": 4}
    provenance = results["policies_recording"]["provenance"]
    assert (provenance["steady"], provenance["seed"], provenance["episodes"]) == (False, 0, 4)
    assert "forecaster trained on the policies' recording (in-sample)" in (work / "results.md").read_text()
    assert (work / "bc_with_forecasts_seed0" / "checkpoints" / "last").is_file()
    assert not list(work.glob("*held*")) and not (work / "push_forecaster").exists()


def test_bc_push_given_forecaster_is_neither_kind_and_has_with_runs_of_its_own(tmp_path):
    work = tmp_path / "work"
    common = ["--quick", "--work", str(work), *PLAIN]
    given = parse_args([*common, "--forecaster", "runs/some/checkpoints"])
    assert not given.held_out_forecaster and not given.in_sample_forecaster
    assert given.out == work / "given"
    assert policy_run_dir(given, "with", 0, 0) == work / "bc_with_given_forecasts_seed0"
    assert policy_run_dir(given, "without", 0, 0) == work / "bc_without_forecasts_seed0"
    round_dir = work / "dagger_markov_given_seed0_round1"  # its episodes were played by the with policies
    assert policy_run_dir(given, "without", 0, 1) == round_dir / "bc_without_forecasts"
    in_sample = parse_args([*common, "--in-sample-forecaster"])
    assert in_sample.out == work
    assert policy_run_dir(in_sample, "with", 0, 0) == work / "bc_with_forecasts_seed0"
    uncalibrated_first = parse_args(
        [*common, "--forecaster", "runs/some/checkpoints", "--no-calibrate", "--forecast-steps", "1"]
    )
    assert uncalibrated_first.out == work / "first1_given"
    assert policy_run_dir(uncalibrated_first, "with", 0, 0) == (
        work / "bc_with_uncalibrated_first1_given_forecasts_seed0"
    )
    default, named = parse_args(common), parse_args([*common, "--held-out-forecaster"])
    for held_out in (default, named):  # the flag of the held-out forecaster is the default's
        assert held_out.held_out_forecaster and held_out.out == work / "heldout"
        assert policy_run_dir(held_out, "with", 0, 0) == work / "bc_with_heldout_forecasts_seed0"


def test_bc_push_with_run_records_its_forecaster_and_refuses_another(tmp_path):
    run = tmp_path / "work" / "bc_with_given_forecasts_seed0"
    trained_on, other = tmp_path / "mine" / "checkpoints", tmp_path / "other" / "checkpoints"
    record_or_check_forecaster(run, trained_on, new_run=True)
    record_or_check_forecaster(run, trained_on, new_run=False)  # the same forecaster: reused
    with pytest.raises(ValueError, match="use another --work") as refused:
        record_or_check_forecaster(run, other, new_run=False)
    assert all(str(p) in str(refused.value) for p in (run, trained_on.resolve(), other.resolve()))
    record_or_check_forecaster(run, other, new_run=True)  # nothing trained yet: the run is the new one's
    record_or_check_forecaster(run, other, new_run=False)
    older = tmp_path / "work" / "bc_with_forecasts_seed0"  # trained before runs kept a record
    older.mkdir()
    record_or_check_forecaster(older, other, new_run=False)
    assert not (older / "forecaster.json").exists()


def test_bc_push_given_forecaster_trains_its_own_with_policy_and_refuses_another_in_the_same_work(
    plain_run, recorded_push_root, push_cache_dir, tmp_path, capsys, short_episodes
):
    work = copied_work(plain_run, tmp_path)  # the in-sample policies, trained
    in_sample_with = work / "bc_with_forecasts_seed0"
    trained = {p: p.stat().st_mtime_ns for p in in_sample_with.rglob("*")}
    assert trained, "the plain run trained the in-sample with policy: what must be left alone"
    ordinary_results = (work / "results.json").read_text()
    for name in ("mine", "other"):  # a user's forecasters, here copies of the in-sample one
        shutil.copytree(work / "forecaster", tmp_path / name)
    mine, other = (tmp_path / name / "checkpoints" for name in ("mine", "other"))

    assert cli(tiny_argv(recorded_push_root, push_cache_dir, work, forecaster=mine, dagger=False)) == 0
    assert_one_outage_summary(capsys.readouterr().out)
    results = json.loads((work / "given" / "results.json").read_text())
    assert "train BC with seed 0" in results["phases_s"]
    assert "train BC without seed 0" not in results["phases_s"], "the ordinary without policy is reused"
    run = work / "bc_with_given_forecasts_seed0"
    assert (run / "checkpoints" / "last").is_file()
    assert json.loads((run / "forecaster.json").read_text()) == {"checkpoints": str(mine.resolve())}
    assert {p: p.stat().st_mtime_ns for p in in_sample_with.rglob("*")} == trained
    assert (work / "results.json").read_text() == ordinary_results, "the in-sample results are left alone"

    capsys.readouterr()
    assert cli(tiny_argv(recorded_push_root, push_cache_dir, work, forecaster=other, dagger=False)) == 1
    err = capsys.readouterr().err
    refusal = err.strip().splitlines()[-1]  # after the in-sample warning's log line
    assert refusal.startswith("bc_push: error: ") and "use another --work" in refusal
    assert "Traceback" not in err
    assert all(str(p) in refusal for p in (run, mine.resolve(), other.resolve()))
    assert json.loads((run / "forecaster.json").read_text()) == {"checkpoints": str(mine.resolve())}


def test_bc_push_warns_when_a_given_forecaster_was_trained_on_the_policies_recording(tmp_path, caplog):
    recording = (tmp_path / "push").resolve()
    trained_on = {"path": str(recording), "seed": None, "episodes": None}
    forecaster = Forecaster(Path("runs/some/checkpoints"), (), None, trained_on)
    with caplog.at_level(logging.WARNING, logger="mmf_rl"):
        warn_of_in_sample_forecasts(forecaster, tmp_path / "other")
        assert not caplog.records, "another recording: no warning"
        warn_of_in_sample_forecasts(forecaster, recording)
        warn_of_in_sample_forecasts(forecaster, None)  # the policies read the forecaster's own recording
    assert len(caplog.records) == 2
    assert all("BC with a held-out forecaster" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    "extra, refusal",
    [
        (["--forecaster", "runs/some/checkpoints", "--held-out-forecaster"], "--forecaster with --held-out"),
        (["--forecaster", "runs/some/checkpoints", "--in-sample-forecaster"], "--forecaster with --held-out"),
        (["--forecaster-data", "DATA"], "is the policies' recording"),
        (["--forecaster-override", "data.root=DATA"], "with --forecaster-data"),
        (["--in-sample-forecaster", "--held-out-forecaster"], "--in-sample-forecaster with --held-out"),
        (["--in-sample-forecaster", "--forecaster-data", "DATA"], "--in-sample-forecaster with --held-out"),
    ],
)
def test_bc_push_refuses_a_forecaster_whose_training_data_contradicts_its_options(
    recorded_push_root, push_cache_dir, tmp_path, capsys, extra, refusal
):
    argv = tiny_argv(recorded_push_root, push_cache_dir, tmp_path / "work", forecaster="held-out")
    extra = [a.replace("DATA", str(recorded_push_root)) for a in extra]
    assert cli([*argv, *extra]) == 2
    assert refusal in capsys.readouterr().err
    assert not (tmp_path / "work").exists()


def test_bc_push_defaults_are_steady_demonstrations_chunks_of_8_and_the_precision_latch(tmp_path, capsys):
    work = tmp_path / "work"
    default = parse_args(["--quick", "--work", str(work)])
    assert default.steady_demonstrations and default.action_chunk == 8
    assert default.latched_forecast == "precision" and default.held_out_forecaster
    assert default.forecast_target == "absolute" and default.out == work / "steady_chunk8_heldout_absolute"
    assert policy_run_dir(default, "with", 0, 0) == (
        work / "bc_steady_chunk8_with_latched_precision_heldout_absolute_forecasts_seed0"
    )
    assert forecaster_run_dir(default) == (work / "forecaster_held_out_absolute").resolve()
    gripper = parse_args(["--work", str(work), "--forecast-target", "gripper"])
    assert gripper.out == work / "steady_chunk8_heldout"  # the earlier default's runs keep their names
    assert forecaster_run_dir(gripper) == (work / "forecaster_held_out").resolve()
    assert parse_args(["--work", str(work)]).record_episodes == 1000
    given = parse_args(["--work", str(work), "--data", "mine", "--latched-forecast", "none"])
    assert not given.steady_demonstrations and given.latched_forecast is None  # --data is used as it is
    drawn = parse_args(["--work", str(work), "--demonstrations", "drawn"])
    assert not drawn.steady_demonstrations and drawn.out == work / "chunk8_heldout_absolute"
    with pytest.raises(SystemExit):
        parse_args(["--work", str(work), "--demonstrations", "drawn", "--data", "mine"])
    assert "--demonstrations drawn records the policies' recording, but --data" in capsys.readouterr().err
