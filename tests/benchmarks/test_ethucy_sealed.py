"""benchmarks/ethucy.py's sealed protocol (``--select``): the options it takes, the protocol every row
records and the reuse check of it, the choice the selection stage makes and records (on fabricated
runs: no data, no training), and a sealed run end to end on a cut of the real ETH/UCY files, which
reads the test scene only in its final stage."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from benchmarks import ethucy as bench
from benchmarks.pedestrians import sealed
from benchmarks.pedestrians.recipe import (
    CV,
    CV_NOISE,
    CV_RECIPES,
    OPTIONS,
    PAPER,
    PAPER_PRIOR,
    QUICK,
    TRAINED,
    Budget,
    given_by_hand,
    protocol,
    recipe,
    run_path,
    slug,
    stale_runs,
)
from benchmarks.pedestrians.scoring import METRICS, MODES
from tests.benchmarks.conftest import ethucy_fold_configs

ROTATION = ["--select", "augment.rotation=0,180"]
EVERY_OPTION = [*ROTATION, "--select", "augment=lerobot,none", "--select", "sampler=5/5,20/10"]


def bench_args(tmp_path: Path, *flags: str):
    return bench.parse_args(["--out", str(tmp_path / "out"), "--data", str(tmp_path / "data"), *flags])


def write_scores(path: Path, **fields) -> None:
    path.mkdir(parents=True, exist_ok=True)
    (path / "scores.json").write_text(json.dumps({"scores": {}, **fields}))


def test_select_spells_each_value_one_way_and_refuses_what_is_no_choice(tmp_path, capsys):
    args = bench_args(tmp_path, "--select", "augment.rotation=0,180.0", "--select", "sampler=5/5,20.0/10")
    assert args.select == {"augment.rotation": ["0", "180"], "sampler": ["5/5", "20/10"]}
    assert bench_args(tmp_path).select == {}
    refused = {
        "augment.rotation=180": "a choice needs two values or more",
        "augment.rotation=180,180.0": "a choice needs two values or more",
        "rotation=0,180": "unknown option 'rotation'",
        "sampler=5,20/10": "expected WEIGHT/SCALE",
        "augment=lerobot,flip": "expected none, lerobot or crop",
    }
    for spec, reason in refused.items():
        with pytest.raises(SystemExit):
            bench_args(tmp_path, "--select", spec)
        assert reason in capsys.readouterr().err
    with pytest.raises(SystemExit):
        bench_args(tmp_path, *ROTATION, *ROTATION)
    assert "--select augment.rotation given twice" in capsys.readouterr().err


def test_a_row_is_sealed_only_when_the_selection_chose_every_option_it_reads(tmp_path):
    probe, rotation, every = (bench_args(tmp_path, *flags) for flags in ([], ROTATION, EVERY_OPTION))
    assert [protocol(probe, label) for label in TRAINED] == ["probe"] * 3
    assert given_by_hand(probe, TRAINED) == ["augment=lerobot", "augment.rotation=180", "sampler=5/5"]
    assert given_by_hand(rotation, TRAINED) == ["augment=lerobot", "sampler=5/5"]
    assert given_by_hand(rotation, ["LF-LSTM"]) == ["augment=lerobot"]  # a baseline reads no sampler
    assert [protocol(every, label) for label in TRAINED] == ["sealed"] * 3
    settings = recipe(
        every, QUICK, "eth", PAPER, {"augment": "none", "augment.rotation": "0", "sampler": "20/10"}
    )
    assert {"augment=none", "augment.rotation=0", "sampler.diversity_weight=20.0", "protocol=sealed"} <= set(
        settings
    )
    assert [s for s in settings if s.startswith(("candidates.", "chosen."))] == [
        "candidates.augment=lerobot,none",
        "candidates.augment.rotation=0,180",
        "candidates.sampler=5/5,20/10",
        "chosen.augment=none",
        "chosen.augment.rotation=0",
        "chosen.sampler=20/10",
    ]
    assert "protocol=probe" in recipe(probe, QUICK, "eth", "MulT")
    assert [s for s in recipe(every, QUICK, "eth", CV_NOISE) if s.startswith("heading_noise_chosen_on")] == [
        "heading_noise_chosen_on=held_out_scenes"
    ]


def test_a_probe_row_is_refused_by_a_sealed_invocation_which_reuses_its_own_rows(tmp_path):
    probe, rotation = bench_args(tmp_path), bench_args(tmp_path, *ROTATION)
    write_scores(run_path(probe, "eth", "MulT"), recipe=recipe(probe, QUICK, "eth", "MulT"))
    assert stale_runs(probe, QUICK, ["eth"]) == []
    [line] = stale_runs(rotation, QUICK, ["eth"])
    assert line.startswith(
        f"{run_path(probe, 'eth', 'MulT')}: candidates.augment.rotation: expected 0,180, found"
    )
    # Checked with the choice it records, whichever of the candidates it is.
    write_scores(
        run_path(probe, "eth", "MulT"),
        recipe=recipe(rotation, QUICK, "eth", "MulT", {"augment.rotation": "0"}),
    )
    assert stale_runs(rotation, QUICK, ["eth"]) == []
    assert "protocol: expected probe, found probe" not in " ".join(stale_runs(probe, QUICK, ["eth"]))
    assert "chosen.augment.rotation: expected absent, found 0" in stale_runs(probe, QUICK, ["eth"])[0]
    other = bench_args(tmp_path, "--select", "augment.rotation=0,90")
    assert "candidates.augment.rotation: expected 0,90, found 0,180" in stale_runs(other, QUICK, ["eth"])[0]


def test_an_inner_run_of_another_recipe_is_refused_and_one_run_serves_every_candidate_training_alike(
    tmp_path,
):
    rotation = bench_args(tmp_path, *ROTATION)
    candidate = {"augment.rotation": "0"}
    path = run_path(rotation, "eth+hotel", PAPER, candidate)
    assert (
        path
        == rotation.out
        / "select"
        / "eth+hotel"
        / "paper_model"
        / "augment_lerobot_augment_rotation_0_sampler_5_5"
    )
    # The same training under another selection: the options it does not select take their hand values.
    assert run_path(
        bench_args(tmp_path, "--select", "sampler=5/5,20/10"), "eth+hotel", PAPER, {"sampler": "5/5"}
    ) == (run_path(rotation, "eth+hotel", PAPER, {"augment.rotation": "180"}))
    seed_1 = bench_args(tmp_path, *ROTATION, "--seed", "1")
    write_scores(path, recipe=recipe(seed_1, QUICK, "eth+hotel", PAPER, candidate), held_out={})
    assert not any(s.startswith("protocol=") for s in recipe(seed_1, QUICK, "eth+hotel", PAPER, candidate))
    assert stale_runs(rotation, QUICK, ["eth"]) == [f"{path}: trainer.seed: expected 0, found 1"]
    assert stale_runs(seed_1, QUICK, ["eth"]) == []
    assert stale_runs(bench_args(tmp_path, "--seed", "1"), QUICK, ["eth"]) == []  # a probe reads no inner run


def test_the_selection_chooses_the_lower_mean_inner_score_per_model_and_records_it(tmp_path, monkeypatch):
    """Inner runs and their scores fabricated: the paper model scores lower turned, the baselines unturned;
    nothing is ever asked of the fold's own scene."""
    args = bench_args(tmp_path, *ROTATION)
    asked = []

    def held_out_score(args, pair, label, candidate, scene, data):
        asked.append((pair, scene))
        turned = candidate["augment.rotation"] == "180"
        return {"hotel": 0.2, "univ": 0.4}.get(scene, 0.3) + (0.01 if turned != (label == PAPER) else 0.0)

    monkeypatch.setattr(sealed, "inner_run", lambda *_: None)
    monkeypatch.setattr(sealed, "held_out_score", held_out_score)
    noise = {
        "0.05": {"hotel": 0.3, "univ": 0.5},
        "0.1": {"hotel": 0.2, "univ": 0.6},
        "0.15": {"hotel": 0.4, "univ": 0.4},
    }
    monkeypatch.setattr(sealed, "held_out_heading_noise", lambda *_: noise)
    chosen, sigma = sealed.select_fold(args, QUICK, "eth")
    assert chosen == {
        PAPER: {"augment.rotation": "180"},
        "LF-LSTM": {"augment.rotation": "0"},
        "MulT": {"augment.rotation": "0"},
    }
    assert sigma == 0.05  # 0.05 and 0.15 tie at 0.4: the first of the grid
    assert {scene for _, scene in asked} == {"hotel", "univ", "zara1", "zara2"}
    assert all(pair.startswith("eth+") or pair.endswith("+eth") for pair, _ in asked)
    record = json.loads((args.out / "eth" / "selection.json").read_text())
    assert record["options"] == {"augment.rotation": ["0", "180"]}
    paper = record["models"][PAPER]
    assert paper["inner_min_ade20"]["augment.rotation=0"] == pytest.approx(
        {
            "hotel": 0.21,
            "univ": 0.41,
            "zara1": 0.31,
            "zara2": 0.31,
        }
    )
    assert paper["mean"] == pytest.approx({"augment.rotation=0": 0.31, "augment.rotation=180": 0.3})
    assert paper["chosen"] == {"augment.rotation": "180"}
    assert record["models"][CV_NOISE]["chosen"] == 0.05


def test_a_final_row_trained_with_another_choice_than_the_selections_is_refused(tmp_path):
    args = bench_args(tmp_path, *ROTATION)
    write_scores(
        run_path(args, "zara1", PAPER), recipe=recipe(args, QUICK, "zara1", PAPER, {"augment.rotation": "0"})
    )
    assert bench.reused(args, QUICK, "zara1", PAPER, {"augment.rotation": "0"})["recipe"]
    with pytest.raises(
        SystemExit,
        match=r"paper_model was trained with another choice than the selection makes now: "
        r"augment.rotation: expected 180, found 0; .*chosen.augment.rotation: expected 180, found 0",
    ):
        bench.reused(args, QUICK, "zara1", PAPER, {"augment.rotation": "180"})


def _scores(value: float) -> dict:
    return {mode: {m: value for m in METRICS} | {"windows": 9.0} for mode in MODES}


def test_the_page_and_the_summary_say_which_protocol_each_row_followed(tmp_path):
    probe, every = bench_args(tmp_path), bench_args(tmp_path, *EVERY_OPTION)
    assert bench.protocol_summary(probe, QUICK) == (
        "probe, seen test: augment=lerobot, augment.rotation=180, sampler=5/5 given by hand"
    )
    assert bench.protocol_summary(every, QUICK) == "sealed"
    section = "\n".join(bench.protocol_section(bench_args(tmp_path, *ROTATION), QUICK))
    assert "- paper model: probe, seen test: augment=lerobot, sampler=5/5 given by hand" in section
    assert (
        "- constant velocity + heading noise: its std chosen on the fold's training scenes held out"
        in section
    )
    rows = {label: {"scores": _scores(0.5)} for label in [*TRAINED, PAPER_PRIOR, CV, CV_NOISE]}
    rows[PAPER]["recipe"] = recipe(
        every, QUICK, "eth", PAPER, {"augment": "lerobot", "augment.rotation": "0", "sampler": "5/5"}
    )
    rows[CV_NOISE] |= {"heading_noise": 0.1, "recipe": recipe(every, QUICK, "eth", CV_NOISE)}
    page = bench.markdown({"eth": rows}, {}, QUICK, "trajectron", {}, bench.protocol_section(every, QUICK))
    assert (
        "- LF-LSTM: sealed: augment, augment.rotation chosen per fold on its training scenes held out" in page
    )
    assert (
        "## eth (9 test windows; heading noise std 0.1 rad, chosen on the held-out training scenes)" in page
    )
    assert (
        "Chosen on the held-out training scenes: paper model: augment=lerobot augment.rotation=0 sampler=5/5."
        in page
    )


# A budget of a few steps, the eth fold only: the pipeline, not a result.
MICRO = Budget("micro: models trained on fold eth; 2 steps", ("eth",), 2, 8, 2, 8, 2, 1)


def eth_episodes(data: Path) -> set[int]:
    """Every episode of the eth scene: its whole file (the eth fold's test) and its _train/_val files
    (in the hotel fold's training and val splits, not in the eth fold's)."""
    import yaml

    eth, hotel = (yaml.safe_load((data / f"{fold}.yaml").read_text())["split"] for fold in ("eth", "hotel"))
    parts = [set(hotel[name]) - set(eth[name]) for name in ("train", "val")]
    return set(eth["test"]).union(*parts)


# Two of the heading noise grid's values: the constant-velocity row's std is still chosen on the held-out
# scenes, each value scored on every one of them (of every fold, in both invocations).
MICRO_HEADING_NOISE_GRID = (0.05, 0.3)


@pytest.mark.slow
@pytest.mark.timeout(3600)  # 6 min with eleven 2-step trainings and two invocations; 28 under heavy load
def test_a_sealed_run_reads_the_test_scene_only_in_its_final_stage(tmp_path, monkeypatch, ethucy_cut):
    """On a cut of the real files (converted once for the session, `ethucy_cut`), fold eth at a micro
    budget, the sampler's weights selected: every batch and every split of the selection stage holds no
    window of eth; eth is read only once its final stage has begun. A second invocation reuses every
    run."""
    import mmf_rl
    from mmf_rl.datasets import WindowDataset

    raw, data = ethucy_cut[0], ethucy_fold_configs(ethucy_cut[1], tmp_path / "data")
    stage, read, split, trained = ["selection"], [], [], []
    monkeypatch.setattr(bench, "QUICK", MICRO)
    for module in (bench, sealed):
        monkeypatch.setattr(module, "HEADING_NOISE_GRID", MICRO_HEADING_NOISE_GRID)
    grid = f"heading_noise_grid={list(MICRO_HEADING_NOISE_GRID)}"
    monkeypatch.setitem(CV_RECIPES, CV_NOISE, [grid])  # the rows' recipe says which grid
    # No image transforms: their worker process costs each training tens of seconds to start, and what
    # is tested is which data each stage reads.
    monkeypatch.setitem(OPTIONS, "augment", dataclasses.replace(OPTIONS["augment"], default="none"))
    batch, init, fold_data, train = WindowDataset.batch, WindowDataset.__init__, bench.fold_data, mmf_rl.train

    def recorded_batch(self, window_ids, *args, **kwargs):
        read.append((stage[0], set(self.window_episode[window_ids].tolist())))
        return batch(self, window_ids, *args, **kwargs)

    def recorded_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        split.append((stage[0], set().union(*map(set, self.split_episodes.values()))))

    def final_stage(args, fold):
        stage[0] = "final"
        return fold_data(args, fold)

    def recorded_train(config):
        trained.append((stage[0], Path(config.data.root), str(config.run_dir)))
        return train(config)

    monkeypatch.setattr(WindowDataset, "batch", recorded_batch)
    monkeypatch.setattr(WindowDataset, "__init__", recorded_init)
    monkeypatch.setattr(bench, "fold_data", final_stage)
    monkeypatch.setattr(mmf_rl, "train", recorded_train)
    paths = ["--raw", str(raw), "--data", str(data), "--out", str(tmp_path / "out")]
    argv = ["--quick", *paths, "--select", "sampler=5/5,20/10", "--batch-size", "64"]
    assert bench.main(argv) == 0

    eth = eth_episodes(data)
    assert eth and any(stage == "selection" for stage, _ in read)
    assert all(not episodes & eth for stage, episodes in [*read, *split] if stage == "selection")
    assert any(episodes & eth for stage, episodes in read if stage == "final")
    # Four pairs holding eth out, two sampler settings: eight inner trainings, then the three final ones.
    assert [stage for stage, _, _ in trained] == ["selection"] * 8 + ["final"] * 3
    assert all("/select/eth+" in run or "+eth/" in run for stage, _, run in trained if stage == "selection")
    out = tmp_path / "out"
    record = json.loads((out / "eth" / "selection.json").read_text())
    means = record["models"][PAPER]["mean"]
    assert set(means) == {"sampler=5/5", "sampler=20/10"}
    assert all(
        set(per) == {"hotel", "univ", "zara1", "zara2"}
        for per in record["models"][PAPER]["inner_min_ade20"].values()
    )
    assert record["models"][PAPER]["chosen"] == {"sampler": min(means, key=means.get).split("=")[1]}
    settings = json.loads((out / "eth" / slug(PAPER) / "scores.json").read_text())["recipe"]
    assert f"chosen.sampler={record['models'][PAPER]['chosen']['sampler']}" in settings
    assert "protocol=probe" in settings  # augment and augment.rotation given by hand
    summary = (out / "results.md").read_text().splitlines()[-1]
    assert summary.endswith("; probe, seen test: augment=none, augment.rotation=180 given by hand)")

    trained.clear()
    assert bench.main(argv) == 0
    assert trained == []
