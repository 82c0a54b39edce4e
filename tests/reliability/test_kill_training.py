"""SIGKILL during `mmf-rl train`, twice in a row, then resume: the weights of an uninterrupted run.

The heavier loop (more kills, more steps) is `benchmarks/kill_loop.py`; this is its 2-kill version.
"""

import random

from benchmarks.kill_loop import final_weights, kill_repeatedly, run_overrides, weights_match
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
    with single_thread():
        assert cli(["train", *overrides("killed"), "resume=true"]) == 0
    ok, gap = weights_match(final_weights(tmp_path / "reference"), final_weights(tmp_path / "killed"))
    assert ok, f"resumed weights differ from the uninterrupted run's by up to {gap}"
