"""benchmarks/real_humanoid.py: the entries' configs, the bootstrap blocks, the summary line, and an
end-to-end smoke run on the real G1 recording."""

from __future__ import annotations

import json
import re
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from tests.conftest import load_benchmark

humanoid = load_benchmark("real_humanoid")
bench = humanoid.bench  # benchmarks/accuracy.py, as the script imports it
SUBSETS = [name for name, _ in bench.subsets(humanoid.MODALITIES)]
SUMMARY = re.compile(
    r"summary: all sensors paper MSE (\S+) vs best baseline (\S+) \((.+)\): paper/best = (\S+) "
    r"\(target <= 1\.05\); mean degradation without a sensor paper (\S+), best baseline (\S+)"
)


def cell(mean: float) -> bench.Cell:
    return bench.Cell(mean, mean - 0.01, mean + 0.01, [mean], 10, torch.full((4,), mean))


def make_table(levels: dict[str, tuple[str, float, dict[str, float]]]) -> bench.Table:
    """``{label: (kind, all-sensor MSE, {subset: MSE / all-sensor MSE})}``; unlisted subsets: ratio 1.1."""
    table = bench.Table(subsets=bench.ordered_subsets(SUBSETS))
    for label, (kind, level, ratios) in levels.items():
        table.kinds[label] = kind
        table.cells[label] = {s: cell(level * ratios.get(s, 1.0 if s == "all" else 1.1)) for s in SUBSETS}
    return table


def test_subsets_are_the_three_sensors_and_read_as_the_issue_names_them():
    assert SUBSETS == [
        "all",
        "without_cam_high",
        "without_state",
        "without_action",
        "only_cam_high",
        "only_state",
        "only_action",
    ]
    titles = [humanoid.subset_title(s) for s in SUBSETS]
    assert titles == [
        "all sensors",
        "without camera",
        "without joints",
        "without commands",
        "camera only",
        "joints only",
        "commands only",
    ]


def test_summary_compares_the_paper_with_the_best_baseline_and_the_most_robust_one():
    table = make_table(
        {
            "paper": (
                "paper",
                0.60,
                {"without_cam_high": 1.02, "without_state": 1.04, "without_action": 1.06},
            ),
            "paper GRU vector encoders (issue #6)": ("variant", 0.40, {}),  # not a baseline
            "LF-LSTM": (
                "zero-fill",
                0.57,
                {"without_cam_high": 1.0, "without_state": 1.9, "without_action": 2.0},
            ),
            "MulT": (
                "zero-fill",
                0.50,
                {"without_cam_high": 1.1, "without_state": 2.5, "without_action": 2.4},
            ),
            "MVAE": (
                "zero-fill",
                0.90,
                {"without_cam_high": 1.0, "without_state": 1.3, "without_action": 1.2},
            ),
        }
    )
    line, summary = humanoid.summarize(table)
    match = SUMMARY.fullmatch(line)
    assert match, line
    assert match.groups() == ("0.6000", "0.5000", "MulT", "1.200", "4%", "17%")
    assert summary["best_baseline"] == "MulT" and summary["most_robust_baseline"] == "MVAE"
    assert summary["ratio_target_met"] is False
    # The only_* subsets (1.1 everywhere) do not enter the degradation without a sensor.
    assert summary["paper_mean_degradation_without_a_sensor"] == pytest.approx(0.04)
    assert summary["best_baseline_mean_degradation_without_a_sensor"] == pytest.approx(1 / 6)

    table.cells["paper"]["all"] = cell(0.52)
    assert humanoid.summarize(table)[1]["ratio_target_met"] is True


def test_summary_says_what_the_run_lacks():
    table = make_table({"paper": ("paper", 0.6, {}), "LF-LSTM": ("zero-fill", 0.5, {})})
    del table.cells["LF-LSTM"]["without_state"]  # a baseline without every subset has no mean degradation
    line, summary = humanoid.summarize(table)
    assert SUMMARY.fullmatch(line), line
    assert "(LF-LSTM): paper/best = 1.200" in line and line.endswith("paper 10%, best baseline -")
    del table.kinds["LF-LSTM"], table.cells["LF-LSTM"]
    line, summary = humanoid.summarize(table)
    assert "vs best baseline - (-): paper/best = - (target" in line
    assert summary["ratio_target_met"] is None


def rows(windows: list[int], episodes: list[int], errors: list[float] | None = None) -> dict:
    return {"window": windows, "episode": episodes, "squared_error": errors or [1.0] * len(windows)}


def test_blocks_are_consecutive_test_windows_of_one_episode_and_the_same_in_every_row():
    # Episode 7's test windows are 100..144, episode 9's 200..209; one subset lost windows 100 and 101.
    full = rows([*range(100, 145), *range(200, 210)], [7] * 45 + [9] * 10)
    partial = rows(list(range(102, 145)), [7] * 43)
    errors = {"paper": {"all": [full], "only_state": [partial]}, "MulT": {"all": [dict(full)]}}
    assert humanoid.bootstrap_unit(errors) == "block"
    blocks = full["block"]
    assert blocks[:20] == [(7, 0)] * 20 and blocks[20:40] == [(7, 1)] * 20 and blocks[40:45] == [(7, 2)] * 5
    assert blocks[45:] == [(9, 0)] * 10  # a block never crosses episodes
    assert partial["block"] == blocks[2:45]  # numbered from the episode's first window in any row
    assert errors["MulT"]["all"][0]["block"] == blocks


def test_enough_test_episodes_are_resampled_as_episodes():
    episodes = list(range(humanoid.MIN_EPISODES))
    errors = {"paper": {"all": [rows([10 * e for e in episodes], episodes)]}}
    assert humanoid.bootstrap_unit(errors) == "episode"
    assert "block" not in errors["paper"]["all"][0]


def test_block_bootstrap_intervals_come_from_accuracys_paired_bootstrap():
    """One test episode: an episode bootstrap has a zero-width interval; blocks give a real one."""
    g = torch.Generator().manual_seed(0)
    errors = (torch.linspace(0.2, 2.0, 100) * (1 + 0.1 * torch.rand(100, generator=g))).tolist()
    per_subset = {s: [rows(list(range(100)), [4] * 100, errors)] for s in SUBSETS}
    table, groups = bench.build_table(
        {"paper": per_subset},
        {"paper": "paper"},
        humanoid.MODALITIES,
        unit=humanoid.bootstrap_unit({"paper": per_subset}),
    )
    assert len(groups) == 5
    c = table.cells["paper"]["all"]
    assert c.mean == pytest.approx(sum(errors) / 100)
    assert c.low < c.mean < c.high


def test_every_entry_composes_the_g1_data_and_its_model(tmp_path):
    from mmf_rl.configuration import compose_config, to_container
    from mmf_rl.datasets import DataConfig

    budget = bench.Budget(image_size=32, batch_size=64, steps=1000, seeds=(0,), entries=None, episodes=6)
    args = SimpleNamespace(data=tmp_path / "g1", out=tmp_path / "out", device="cpu")
    composed = {
        e.label: compose_config("train", bench.train_overrides(e, 0, budget, args, tmp_path / "run"))
        for e in humanoid.ENTRIES
    }
    assert list(composed)[0] == "paper"
    data = {label: DataConfig.from_dict(to_container(cfg.data)) for label, cfg in composed.items()}
    for label, d in data.items():
        assert Path(d.root) == tmp_path / "g1" and list(d.image_size) == [32, 32], label
        assert {m: c.feature for m, c in d.modalities.items()} == {
            "cam_high": "observation.images.cam_high",
            "state": "observation.state",
            "action": "action",
        }, label
        assert (d.target.feature, d.target.relative, d.target.dims) == ("observation.state", True, None)
        assert (d.history, d.horizon, list(d.split_fractions), d.split_seed) == (10, 10, [0.8, 0.1, 0.1], 0)
        assert (composed[label].trainer.total_steps, composed[label].trainer.batch_size) == (1000, 64)
    assert {label: cfg.model.name for label, cfg in composed.items()} == {
        "paper": "forecaster",
        "paper prior=learned": "forecaster",
        "paper GRU vector encoders (issue #6)": "forecaster",
        "paper, mixed tokens, per-frame camera tokens": "forecaster",
        "LF-LSTM": "lf_lstm",
        "MulT": "mult",
        "MVAE": "mvae",
    }
    issue6 = "paper GRU vector encoders (issue #6)"
    assert composed["paper"].model == compose_config("train", []).model  # the configuration defaults
    assert (composed[issue6].model.prior, composed["paper prior=learned"].model.prior) == (
        "standard",
        "learned",
    )
    assert [data[issue6].modalities[m].encoder for m in humanoid.MODALITIES] == [None, "gru", "gru"]
    assert all(c.encoder is None for c in data["paper"].modalities.values())  # each kind's default
    frames = "paper, mixed tokens, per-frame camera tokens"
    assert data[frames].modalities["cam_high"].encoder == "conv_frames"
    assert composed[frames].model.decoder_input == "mixed"


def test_a_missing_recording_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit):
        humanoid.main(["--root", str(tmp_path / "nowhere"), "--out", str(tmp_path / "out")])
    assert "no LeRobot dataset there (meta/info.json missing)" in capsys.readouterr().err


needs_g1 = pytest.mark.skipif(
    not (humanoid.DEFAULT_ROOT / "meta" / "info.json").is_file(),
    reason=f"real G1 recording not found at {humanoid.DEFAULT_ROOT} (set MMF_RL_SHARED_DATA)",
)


@needs_g1
def test_smoke_run_on_the_real_recording_writes_the_results_and_resumes(tmp_path, capsys):
    out = tmp_path / "out"
    argv = [
        "--steps",
        "2",
        "--seeds",
        "0",
        "--entries",
        "paper",
        "LF-LSTM",
        "--batch-size",
        "4",
        "--out",
        str(out),
    ]
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert humanoid.main(argv) == 0
        first = capsys.readouterr().out.strip().splitlines()[-1]
        assert SUMMARY.fullmatch(first), first
        results = json.loads((out / "results.json").read_text())
        assert (out / "results.md").read_text().strip().splitlines()[-1] == first
        info = results["info"]
        assert info["split"]["test"] and set(results["cells"]) == {"paper", "LF-LSTM"}
        assert results["subsets"] == bench.ordered_subsets(SUBSETS)
        for cells in results["cells"].values():
            assert set(cells) == set(SUBSETS)
            assert all(c["windows"] == info["test_windows"] for c in cells.values())  # every sensor present
            assert all(c["low"] <= c["mean"] <= c["high"] for c in cells.values())
        assert results["bootstrap"]["unit"] == ("block" if len(info["split"]["test"]) < 10 else "episode")
        assert [r["steps"] for r in results["runs"]["paper"]] == [2]
        # Rerun: both runs are reused, the numbers are the same.
        assert humanoid.main(argv) == 0
        assert capsys.readouterr().out.strip().splitlines()[-1] == first
        assert json.loads((out / "results.json").read_text())["info"]["reused"] == 2
        # Another budget in the same --out is refused before any training.
        with pytest.raises(SystemExit, match=r"holds runs of another budget than 3 steps of batch 4"):
            humanoid.main([*argv, "--steps", "3"])
    finally:
        torch.set_num_threads(threads)
