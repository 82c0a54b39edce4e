"""What the push experiment scripts share: budgets filled into their arguments, merged overrides."""

from __future__ import annotations

import argparse
from pathlib import Path

from mmf_rl.rl.experiment import add_common_arguments, merged_overrides, resolve_budget

BUDGETS = {"quick": {"episodes": 20, "outage": ["episode"]}, "full": {"episodes": 50, "outage": ["dies"]}}


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_common_arguments(parser, "mpc")
    return resolve_budget(parser.parse_args(argv), BUDGETS, "mpc")


def test_the_budget_fills_what_is_not_given_and_names_the_work_directory():
    quick = parse("--quick", "--episodes", "3")
    assert (quick.episodes, quick.outage) == (3, ["episode"])
    assert quick.work == quick.out == Path("runs/bench_mpc_quick")
    full = parse("--out", "elsewhere")
    assert (full.episodes, full.outage, full.work, full.out) == (
        50,
        ["dies"],
        Path("runs/bench_mpc_full"),
        Path("elsewhere"),
    )


def test_extra_overrides_replace_the_same_keys():
    base = ["run_dir=a", "trainer.seed=0", "trainer.total_steps=100"]
    assert merged_overrides(base, ["trainer.total_steps=3", "model.d_model=8"]) == [
        "run_dir=a",
        "trainer.seed=0",
        "trainer.total_steps=3",
        "model.d_model=8",
    ]
