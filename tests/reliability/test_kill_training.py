"""SIGKILL during `mmf-rl train`, twice in a row, then resume: the weights of an uninterrupted run (a
kill, a resume that is killed again, a resume to the end: what a single kill and resume does, twice).

The heavier loop (more kills, more steps) is `benchmarks/kill_loop.py`; this is its 2-kill version.
"""

import random

import torch

from benchmarks.kill_loop import final_weights, kill_repeatedly, run_overrides, weights_match
from mmf_rl.checkpoint import load_checkpoint
from mmf_rl.cli import main as cli
from tests.reliability.conftest import single_thread

TOTAL_STEPS = 16


def test_two_sigkills_then_resume_end_with_the_weights_of_an_uninterrupted_run(
    recorded_push_root, push_cache_dir, tmp_path
):
    def overrides(run):
        return run_overrides(recorded_push_root, push_cache_dir, tmp_path / run, TOTAL_STEPS)

    with single_thread():
        assert cli(["train", *overrides("reference")]) == 0
    # Every step_* checkpoint is loaded after each kill (kill_when_checkpointed).
    killed_at = kill_repeatedly(
        overrides("killed"),
        tmp_path / "killed" / "checkpoints",
        kills=2,
        total_steps=TOTAL_STEPS,
        rng=random.Random(0),
    )
    assert killed_at[0] < killed_at[1] < TOTAL_STEPS
    # The `last` pointer a resume reads moves once a checkpoint is complete: after the second kill it
    # names the checkpoint of a step trained after the first resume, or the one that resume began at.
    assert killed_at[0] <= load_checkpoint(tmp_path / "killed" / "checkpoints").step <= killed_at[1]
    with single_thread():
        assert cli(["train", *overrides("killed"), "resume=true"]) == 0
    reference, resumed = final_weights(tmp_path / "reference"), final_weights(tmp_path / "killed")
    ok, gap = weights_match(reference, resumed)
    assert ok, f"resumed weights differ from the uninterrupted run's by up to {gap}"
    for name, value in reference.items():  # the first tensor that differs, by name
        torch.testing.assert_close(resumed[name], value, rtol=1e-5, atol=1e-6, msg=name)
