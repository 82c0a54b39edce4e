"""ETH/UCY-style scoring: the four modes on the same windows, averages, the summary line, the figure;
constant velocity on the real test scenes of both window sets (skipped without the data)."""

import numpy as np
import pandas as pd
import pytest
import torch
from tensordict import TensorDict

from benchmarks.pedestrians import scoring
from mmf_rl import keys
from mmf_rl.keys import ModalitySpec
from mmf_rl.models import build_model

HISTORY, HORIZON = 8, 12
SPECS = [
    ModalitySpec("trajectory", "sequence", (4,)),
    ModalitySpec("neighbours", "sequence", (10,)),
    ModalitySpec("scene", "image", (3, 8, 8)),
]


def _walks(n: int, seed: int = 0) -> TensorDict:
    """Straight walks (target in metres, unnormalised) with a lateral kink after the last observed step."""
    g = torch.Generator().manual_seed(seed)
    velocity = torch.randn(n, 1, 2, generator=g)
    past = velocity * torch.arange(-(HISTORY - 1), 1)[None, :, None]
    future = velocity * torch.arange(1, HORIZON + 1)[None, :, None] + torch.tensor([0.0, 0.3])
    data = {keys.TARGET_PAST: past, keys.TARGET: future}
    for spec in SPECS:
        dtype = torch.uint8 if spec.kind == "image" else torch.float32
        data[spec.obs_key] = torch.zeros(n, HISTORY, *spec.shape, dtype=dtype)
        data[spec.present_key] = torch.ones(n, dtype=torch.bool)
    return TensorDict(data, batch_size=[n])


def _scores(ade: float, fde: float, min_ade: float, min_fde: float) -> dict:
    return {"ade": ade, "fde": fde, "min_ade_k": min_ade, "min_fde_k": min_fde}


def test_constant_velocity_scores_the_same_in_every_mode_and_its_error_is_the_kink():
    model = build_model({"name": "constant_velocity"}, SPECS, HISTORY, HORIZON, 2).eval()
    scores = scoring.score_modes(model, [_walks(6), _walks(5, seed=1)], lambda t: t)
    assert list(scores) == list(scoring.MODES)
    for mode in scoring.MODES:
        assert scores[mode]["windows"] == 11
        assert scores[mode]["ade"] == pytest.approx(0.3) and scores[mode]["fde"] == pytest.approx(0.3)
        assert scores[mode]["min_ade_k"] == pytest.approx(scores[mode]["ade"])  # 20 equal samples
    assert scoring.score_modes(model, [_walks(6)], lambda t: t, deterministic=True)["all"][
        "min_fde_k"
    ] == pytest.approx(0.3)


def test_averages_are_over_scenes_and_the_summary_line_has_the_documented_form():
    def model(a: float) -> dict:
        return {mode: _scores(a, 2 * a, a / 2, a) for mode in scoring.MODES}

    per_scene = {
        "eth": {"paper": model(0.2), "cv": model(0.5), "lstm": model(0.4), "mult": model(0.6)},
        "hotel": {"paper": model(0.4), "cv": model(0.7), "lstm": model(0.2), "mult": model(0.2)},
    }
    assert scoring.average_over_scenes(per_scene, ["hotel"])["lstm"]["all"]["ade"] == pytest.approx(0.2)
    per_scene["hotel"].pop("mult")
    average = scoring.average_over_scenes(per_scene)
    assert "mult" not in average
    assert average["paper"]["all"]["min_ade_k"] == pytest.approx(0.15)
    average["paper"]["without_scene"]["min_ade_k"] = 0.2
    line = scoring.summary_line(average, "paper", "cv", ["lstm", "cv"], "quick mode")
    assert line == (
        "summary: paper model minADE20/minFDE20 avg 0.15/0.30 (without scene 0.20/0.30, without "
        "neighbours 0.15/0.30); constant velocity 0.30/0.60; best baseline lstm 0.15/0.30 (quick mode)"
    )
    assert scoring.relative_rise(average["paper"], "without_scene") == pytest.approx(1 / 3)
    table = scoring.scores_table(average, deterministic=["lstm"])
    assert "| lstm | 0.15/0.30 † | 0.30/0.60 |" in table
    assert "AgentFormer (leak fixed) | 0.23 / 0.39" in scoring.published_table()


def test_examples_are_placed_in_the_world_and_drawn_on_the_image(tmp_path):
    batch = _walks(2)
    position = torch.tensor([[10.0, 5.0], [1.0, 1.0]])
    samples = batch.get(keys.TARGET)[:, None].expand(-1, 3, -1, -1)
    examples = scoring.world_examples(
        batch, samples, lambda b: b.get(keys.TARGET_PAST) + position[:, None], lambda t: t
    )
    np.testing.assert_allclose(examples[0]["past"][-1], [10.0, 5.0])
    np.testing.assert_allclose(examples[0]["future"], (batch.get(keys.TARGET)[0] + position[0]).numpy())
    assert examples[1]["samples"].shape == (3, HORIZON, 2)
    image = np.zeros((48, 64, 3), dtype=np.uint8)
    path = scoring.plot_forecasts_on_image(
        image, lambda xy: xy[..., ::-1] + 20, examples, tmp_path / "f.png", "test"
    )
    assert path.stat().st_size > 1000


@pytest.fixture(scope="module")
def eth_fold(ethucy_cut, tmp_path_factory):
    """The eth fold's windows, of the session's cut of the real ETH/UCY files (skipped without them),
    with a window cache of its own."""
    import yaml

    from mmf_rl.datasets import DataConfig, WindowDataset

    config = yaml.safe_load((ethucy_cut[1] / "eth.yaml").read_text())
    cache = tmp_path_factory.mktemp("eth_fold") / "cache"
    return WindowDataset(DataConfig.from_dict(config | {"cache_dir": str(cache), "image_size": [16, 16]}))


def test_constant_velocity_of_a_real_fold_scores_again_the_same_and_repeats_its_sample(eth_fold):
    from benchmarks.pedestrians.scoring import constant_velocity_model, score_split

    plain = score_split(constant_velocity_model(eth_fold), eth_fold, "test", batch_size=8)
    assert plain["all"]["windows"] > 0
    # Without heading noise its 20 samples are one forecast: the best of 20 is that forecast's error.
    assert plain["all"]["min_ade_k"] == pytest.approx(plain["all"]["ade"])
    noisy = constant_velocity_model(eth_fold, heading_noise=0.3)
    first, again = (score_split(noisy, eth_fold, "test", batch_size=8) for _ in range(2))
    assert first == again  # the samples are drawn from a fixed seed
    assert first["all"]["min_ade_k"] < first["all"]["ade"]


def test_heading_noise_is_picked_on_val_as_the_grid_value_of_lowest_min_ade(eth_fold):
    from benchmarks.pedestrians.scoring import best_heading_noise, constant_velocity_model, score_split

    grid = (0.0, 0.2, 1.5)
    best, on_val = best_heading_noise(eth_fold, grid, batch_size=8)
    assert set(on_val) == set(grid) and on_val[best] == min(on_val.values())
    val = score_split(constant_velocity_model(eth_fold, 1.5), eth_fold, "val", batch_size=8)
    assert on_val[1.5] == val["all"]["min_ade_k"]


def _raw_windows(table: pd.DataFrame, first_frames: np.ndarray, agents: np.ndarray) -> torch.Tensor:
    """``[N, 20, 2]`` positions (metres) of the windows of ``agents`` from ``first_frames`` in the raw
    file ``table``."""
    from mmf_rl.datasets import ethucy

    offsets = np.arange(HISTORY + HORIZON) * ethucy.FRAME_STEP
    rows = pd.MultiIndex.from_arrays(
        [np.repeat(agents, len(offsets)), (first_frames[:, None] + offsets).ravel()]
    )
    xy = table.set_index(["agent", "frame"])[["x", "y"]].loc[rows].to_numpy()
    return torch.tensor(xy, dtype=torch.float32).view(len(agents), len(offsets), 2)


def _test_batches(raw, fold: str, window_set: str, batch_size: int = 4096):
    """The fold's test windows of ``window_set`` read straight from its raw files, as the scoring reads
    a batch: the target and its past in metres from the last observed position, the modalities zeros."""
    from mmf_rl.datasets import ethucy

    for _, path in ethucy.fold_files(raw, fold)["test"]:
        table = ethucy.read_sequence(path)
        windows = ethucy.track_windows(table)
        if window_set == "social_gan":
            windows = windows[ethucy.social_gan_windows(windows["frame"].to_numpy())]
        for first in range(0, len(windows), batch_size):
            part = windows.iloc[first : first + batch_size]
            positions = _raw_windows(table, part["frame"].to_numpy(), part["agent"].to_numpy())
            relative = positions - positions[:, HISTORY - 1 : HISTORY]
            batch = _walks(len(part))
            batch.set(keys.TARGET_PAST, relative[:, :HISTORY])
            batch.set(keys.TARGET, relative[:, HISTORY:])
            yield batch


# Constant velocity's ADE/FDE averaged over the five scenes on each window set: on Social-GAN's windows
# as Schöller et al. 2020 published it, on Trajectron++'s as the benchmark recorded it
# (docs/benchmarks/ethucy.md).
PUBLISHED_CONSTANT_VELOCITY = {"social_gan": "0.52/1.14", "trajectron": "0.53/1.15"}


@pytest.mark.parametrize("window_set", sorted(PUBLISHED_CONSTANT_VELOCITY))
def test_constant_velocity_on_the_real_test_scenes_gives_the_published_figure_of_each_window_set(window_set):
    """Scored by the benchmark's metric code in mode ``all`` only: constant velocity reads no modality."""
    from mmf_rl.datasets import ethucy
    from mmf_rl.eval.metrics import evaluate_presence_subsets
    from tests.datasets.conftest import SHARED_DATA

    raw = SHARED_DATA / "ethucy"
    if not (raw / "trajectories" / "all_data").is_dir():
        pytest.skip(f"ETH/UCY data not at {raw} (set MMF_RL_SHARED_DATA)")
    model = build_model({"name": "constant_velocity"}, SPECS, HISTORY, HORIZON, 2).eval()
    per_scene = [
        evaluate_presence_subsets(
            model, _test_batches(raw, fold, window_set), [("all", scoring.MODES["all"])], lambda t: t
        )[0]["all"]
        for fold in sorted(ethucy.FOLDS)
    ]
    average = {metric: np.mean([scores[metric] for scores in per_scene]) for metric in ("ade", "fde")}
    assert scoring.ade_fde_text(average, point=True) == PUBLISHED_CONSTANT_VELOCITY[window_set]
