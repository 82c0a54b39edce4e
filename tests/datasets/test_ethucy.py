"""ETH/UCY -> LeRobot: converted on a slice of the real files (skipped when ../shared is absent)."""

import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from mmf_rl.datasets import ethucy
from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.windows import WindowDataset
from tests.datasets.conftest import SHARED_DATA, cut_ethucy_raw

RAW = SHARED_DATA / "ethucy"
pytestmark = pytest.mark.skipif(
    not (RAW / "trajectories" / "all_data" / "biwi_eth.txt").is_file(),
    reason=f"ETH/UCY data not at {RAW} (set MMF_RL_SHARED_DATA)",
)
SLICE_STEPS = 60  # steps of each file kept


def _slice(sequence: str, steps: int = SLICE_STEPS) -> pd.DataFrame:
    table = ethucy.read_sequence(RAW / "trajectories" / "all_data" / f"{sequence}.txt")
    return table[table["frame"] < table["frame"].min() + steps * ethucy.FRAME_STEP].reset_index(drop=True)


def _with_gap(table: pd.DataFrame) -> tuple[pd.DataFrame, int, np.ndarray]:
    """The longest-tracked agent made to leave for two steps mid-track (the real files have no such
    agent): the table without those rows, the agent, and the frames removed."""
    agent = int(table.groupby("agent").size().idxmax())
    frames = np.sort(table.loc[table["agent"] == agent, "frame"].to_numpy())
    gone = frames[len(frames) // 2 : len(frames) // 2 + 2]
    keep = ~((table["agent"] == agent) & table["frame"].isin(gone))
    return table[keep].reset_index(drop=True), agent, gone


@pytest.fixture(scope="module")
def converted(tmp_path_factory) -> tuple[Path, dict, dict]:
    """A three-split dataset from slices: zara01 (with a leaving agent) / zara03 (no scene) / eth."""
    root = tmp_path_factory.mktemp("ethucy") / "slice"
    zara, agent, gone = _with_gap(_slice("crowds_zara01"))
    tables = {
        "train": [("crowds_zara01", zara)],
        "val": [("crowds_zara03", _slice("crowds_zara03"))],
        "test": [("biwi_eth", _slice("biwi_eth"))],
    }
    split = ethucy.write_dataset(root, tables, RAW)
    config = ethucy.data_config(root, split, ethucy.NeighbourConfig(), ethucy.CropConfig())
    config["cache_dir"] = str(root.parent / "cache")
    return root, config, {"agent": agent, "gone": gone, "tables": tables}


def _frames(root: Path) -> pd.DataFrame:
    return pd.concat(
        [pd.read_parquet(p) for p in sorted((root / "data").rglob("*.parquet"))], ignore_index=True
    ).drop(columns=[ethucy.SCENE_KEY])


def _column(frames: pd.DataFrame, key: str) -> np.ndarray:
    """A feature column as ``[N, d]`` (lerobot stores one-value features as scalars)."""
    return np.stack([np.atleast_1d(v) for v in frames[key].to_numpy()])


def test_slice_converts_to_a_dataset_the_window_pipeline_reads(converted):
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    root, config, _ = converted
    meta = LeRobotDatasetMetadata("local/slice", root=root)
    assert meta.total_episodes == sum(len(v) for v in config["split"].values()) > 0
    assert meta.fps == pytest.approx(2.5)
    windows = WindowDataset(DataConfig.from_dict(config), num_workers=0)
    assert all(len(windows.split_windows[s]) > 0 for s in ("train", "val", "test"))
    batch = windows.batch(windows.split_windows["test"][:5])
    assert batch["target"].shape == (5, ethucy.HORIZON, 2)
    assert batch["obs", "scene"].shape == (5, ethucy.HISTORY, 3, 64, 64)
    # The slots' validity flags stay 0/1 through normalisation, as the deepsets encoder reads them.
    flags = batch["obs", "neighbours"].unflatten(-1, (-1, ethucy.SLOT_DIM))[..., -1]
    assert set(flags.unique().tolist()) <= {0.0, 1.0}
    # zara03 has no reference frame: its windows have the scene absent, the others present.
    val, test = windows.split_windows["val"], windows.split_windows["test"]
    assert not windows.presence["scene"][val].any() and windows.presence["scene"][test].all()
    # Metres back: the denormalised target is the recorded displacement from the current step.
    frames = _frames(root)
    start = int(windows.window_start[test[0]])
    xy = _column(frames, ethucy.TRAJECTORY_KEY)[:, :2]
    now = start + ethucy.HISTORY - 1
    expected = xy[now + 1 : now + 1 + ethucy.HORIZON] - xy[now]
    got = windows.normalizer.denormalize_target(batch["target"][0]).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-4)


def test_every_position_is_an_annotated_one_and_a_leaving_agent_splits_its_track(converted):
    root, config, info = converted
    frames = _frames(root)
    agents = _column(frames, ethucy.AGENT_KEY)[:, 0]
    for name, [(_, table)] in info["tables"].items():
        mine = frames["episode_index"].isin(config["split"][name]).to_numpy()
        written = pd.DataFrame(_column(frames[mine], ethucy.TRAJECTORY_KEY)[:, :2], columns=["x", "y"])
        written["agent"], written["frame"] = agents[mine], _column(frames[mine], ethucy.FRAME_KEY)[:, 0]
        joined = written.merge(table, on=["agent", "frame"], how="left", suffixes=("", "_raw"))
        # Every written position is the annotated one: none zero-filled, none interpolated.
        np.testing.assert_allclose(joined[["x", "y"]], joined[["x_raw", "y_raw"]], atol=1e-5)
    for _, episode in frames.groupby("episode_index"):
        assert (np.diff(_column(episode, ethucy.FRAME_KEY)[:, 0]) == ethucy.FRAME_STEP).all()
    train = frames["episode_index"].isin(config["split"]["train"]).to_numpy()
    mine = frames[train & (agents == info["agent"])]
    assert mine["episode_index"].nunique() == 2, "the agent that leaves and re-enters is two episodes"
    assert not set(_column(mine, ethucy.FRAME_KEY)[:, 0]) & set(info["gone"])


def test_a_frame_without_neighbours_has_only_invalid_slots():
    table = ethucy.with_velocities(_slice("biwi_eth"))
    alone = table.groupby("frame")["agent"].transform("size").to_numpy() == 1
    assert alone.any(), "the eth slice starts with a lone pedestrian"
    slots = ethucy.neighbour_slots(table, ethucy.NeighbourConfig()).reshape(len(table), 8, ethucy.SLOT_DIM)
    assert (slots[alone] == 0).all()
    crowded = table.groupby("frame")["agent"].transform("size").to_numpy()
    # Valid slots: exactly min(K, others) of them, the nearest first.
    np.testing.assert_array_equal(slots[..., 4].sum(1), np.minimum(8, crowded - 1))
    distance = np.hypot(slots[..., 0], slots[..., 1])
    assert (np.diff(distance, axis=1)[slots[:, 1:, 4] == 1] >= 0).all()


def test_a_neighbour_slot_is_one_agent_over_its_steps():
    """With tracks, each slot's steps are the same person's annotated positions back in time (relative
    to the agent now), its newest step the per-frame slot; a step where that person was not annotated,
    as for an agent that leaves and comes back, is zeros with ``seen = 0``."""
    table, agent, gone = _with_gap(_slice("crowds_zara01"))
    table = ethucy.with_velocities(table)
    steps = 4
    tracks = ethucy.neighbour_slots(table, ethucy.NeighbourConfig(8, steps))
    tracks = tracks.reshape(len(table), 8, steps, ethucy.SLOT_DIM)
    frame_only = ethucy.neighbour_slots(table, ethucy.NeighbourConfig())
    frame_only = frame_only.reshape(len(table), 8, ethucy.SLOT_DIM)
    np.testing.assert_array_equal(tracks[:, :, -1], frame_only)
    nearest = ethucy.nearest_agents(table, 8)
    position = {(a, f): (x, y) for a, f, x, y in table[["agent", "frame", "x", "y"]].itertuples(index=False)}
    xy, agents, frames = table[["x", "y"]].to_numpy(), table["agent"].to_numpy(), table["frame"].to_numpy()
    seen_gap = unseen = 0
    for row, slot in zip(*np.nonzero(nearest >= 0), strict=True):
        other = agents[nearest[row, slot]]
        for step in range(steps):
            frame = frames[row] - (steps - 1 - step) * ethucy.FRAME_STEP
            values = tracks[row, slot, step]
            if (other, frame) in position:
                assert values[4] == 1
                relative = np.subtract(position[other, frame], xy[row])
                np.testing.assert_allclose(values[:2], relative, atol=1e-5)
            else:
                assert (values == 0).all()
                unseen += 1
                seen_gap += int(other == agent and frame in gone)
    assert seen_gap > 0 and unseen > seen_gap  # the leaving agent's gap, and tracks that start late
    assert (tracks[nearest < 0] == 0).all()


def _episodes(tables, crop: ethucy.CropConfig, neighbour_steps: int = 1) -> list[dict[str, np.ndarray]]:
    scene = ethucy.load_scene(RAW, "seq_eth")
    neighbours = ethucy.NeighbourConfig(steps=neighbour_steps)
    return ethucy.sequence_episodes(tables, scene, neighbours, crop, ethucy.HISTORY + ethucy.HORIZON)


@pytest.mark.parametrize(("heading", "neighbour_steps"), [(False, 1), (True, 1), (False, ethucy.HISTORY)])
def test_no_input_reads_a_future_position(heading, neighbour_steps):
    """The velocity leak: moving every agent's positions after frame `now` (the agent's own and its
    neighbours', their tracks included) must leave every input of frames up to `now` unchanged."""
    table = _slice("biwi_eth")
    now = int(np.sort(table["frame"].unique())[SLICE_STEPS // 2])
    moved = table.copy()
    future = moved["frame"] > now
    rng = np.random.default_rng(0)
    moved.loc[future, ["x", "y"]] += rng.normal(0.0, 1.0, (int(future.sum()), 2))
    crop = ethucy.CropConfig(heading=heading)
    before, after = _episodes(table, crop, neighbour_steps), _episodes(moved, crop, neighbour_steps)
    assert len(before) == len(after) > 0
    checked = changed = 0
    for a, b in zip(before, after, strict=True):
        past = a[ethucy.FRAME_KEY][:, 0] <= now
        for key in (ethucy.TRAJECTORY_KEY, ethucy.NEIGHBOURS_KEY, ethucy.SCENE_KEY):
            np.testing.assert_array_equal(a[key][past], b[key][past], err_msg=f"{key} reads the future")
        checked += int(past.sum())
        changed += int((a[ethucy.TRAJECTORY_KEY][~past] != b[ethucy.TRAJECTORY_KEY][~past]).any())
    assert checked > 0 and changed > 0  # the test compares real past frames, and the future did move


def _coded_scene(world_to_image) -> ethucy.Scene:
    """A scene whose pixel values spell their own (row, col)."""
    rows, cols = np.meshgrid(np.arange(576), np.arange(720), indexing="ij")
    image = np.stack([rows % 256, cols % 256, rows // 256 * 16 + cols // 256], axis=-1).astype(np.uint8)
    return ethucy.Scene(image, world_to_image)


def _decode(pixel: np.ndarray) -> tuple[int, int]:
    return int(pixel[0]) + 256 * (int(pixel[2]) // 16), int(pixel[1]) + 256 * (int(pixel[2]) % 16)


@pytest.mark.parametrize("name", ["seq_eth", "zara01"])
def test_scene_crop_puts_a_world_point_where_the_map_says(name):
    crop = ethucy.CropConfig(pixels=33, metres=8.25)  # 0.25 m per pixel, centre pixel (16, 16)
    homography = np.loadtxt(RAW / "scenes" / name / "H.txt") if name == "seq_eth" else None
    scene = _coded_scene(None if homography is None else np.linalg.inv(homography))
    centre = np.array([[5.0, 6.0]])
    image = scene.crops(centre, crop)[0]
    for (dx, dy), (i, j) in [((0.0, 0.0), (16, 16)), ((1.0, 0.0), (16, 20)), ((0.0, 1.0), (12, 16))]:
        x, y = centre[0, 0] + dx, centre[0, 1] + dy
        if homography is None:  # the README's UCY formula
            expected = (288 - (y - 6.8734) / 0.023866, 360 + (x - 7.5767) / 0.021047)
        else:  # H maps (row, col, 1) to world (x, y, 1)
            row_col = np.linalg.solve(homography, [x, y, 1.0])
            expected = tuple(row_col[:2] / row_col[2])
        assert _decode(image[i, j]) == tuple(int(round(v)) for v in expected)


def test_crops_outside_the_reference_frame_are_black():
    scene = _coded_scene(None)
    far = scene.crops(np.array([[500.0, 500.0]]), ethucy.CropConfig(pixels=8, metres=2.0))
    assert (far == 0).all()


def test_folds_follow_the_protocol_table():
    files = ethucy.fold_files(RAW, "univ")
    assert [s for s, _ in files["test"]] == ["students001", "students003"]
    assert [s for s, _ in files["train"]] == [s for s, _ in files["val"]]
    assert {s for s, _ in files["train"]} == set(ethucy.SEQUENCES) - {"students001", "students003"}
    assert all(p.name.endswith("_train.txt") for _, p in files["train"])
    with pytest.raises(ValueError, match="unknown ETH/UCY fold 'mars'"):
        ethucy.fold_files(RAW, "mars")


def test_every_file_is_converted_once_and_each_fold_splits_the_parts():
    files = ethucy.part_files(RAW, sorted(ethucy.FOLDS))
    # Each sequence's _train and _val file, and the whole file of the six test sequences.
    assert len(files) == 2 * len(ethucy.SEQUENCES) + 6
    assert files["biwi_eth"] == ("biwi_eth", RAW / "trajectories" / "all_data" / "biwi_eth.txt")
    parts = {part: [10 * i, 10 * i + 1] for i, part in enumerate(sorted(files))}
    split = ethucy.fold_split(RAW, "univ", parts)
    assert split["test"] == sorted(parts["students001"] + parts["students003"])
    assert set(parts["crowds_zara03_train"]) <= set(split["train"])
    assert not set(parts["students001_train"]) & set(split["train"])
    assert not set(split["train"]) & set(split["val"]) and not set(split["val"]) & set(split["test"])
    assert set(ethucy.part_files(RAW, ["eth"])) == {
        *(f"{s}_{kind}" for s in ethucy.SEQUENCES if s != "biwi_eth" for kind in ("train", "val")),
        "biwi_eth",
    }


def test_fold_configs_over_one_dataset_share_one_cache_build(converted):
    from mmf_rl.datasets.cache import cache_path
    from mmf_rl.datasets.lerobot_source import LeRobotSource

    root, config, _ = converted
    everything = sorted(e for ids in config["split"].values() for e in ids)
    split = config["split"]
    swapped = {"train": split["train"], "val": split["test"], "test": split["val"]}
    paths = []
    for fold_split in (split, swapped):
        fold = ethucy.data_config(root, fold_split, ethucy.NeighbourConfig(), ethucy.CropConfig(), everything)
        paths.append(
            cache_path(LeRobotSource(DataConfig.from_dict(fold | {"cache_dir": config["cache_dir"]})))
        )
    assert paths[0] == paths[1]
    # Without the explicit selection, a split that leaves episodes out would key its own build.
    partial = ethucy.data_config(
        root, {"train": split["train"], "test": split["test"]}, ethucy.NeighbourConfig(), ethucy.CropConfig()
    )
    assert (
        cache_path(LeRobotSource(DataConfig.from_dict(partial | {"cache_dir": config["cache_dir"]})))
        != paths[0]
    )


def test_import_command_names_the_missing_files(tmp_path, capsys):
    from mmf_rl.cli import main

    assert main(["import", "ethucy", str(tmp_path), "--out", str(tmp_path / "out"), "--fold", "eth"]) == 1
    error = capsys.readouterr().err
    assert "biwi_hotel_train.txt" in error and "trajectories/{train,val,all_data}/" in error
    assert not (tmp_path / "out" / ethucy.DATASET_NAME).exists()


@pytest.mark.slow
def test_train_and_eval_through_the_cli_report_metres_and_best_of_20(converted, tmp_path):
    """The normal `mmf-rl train data=FILE` / `mmf-rl eval` path on the converted slice, windows turned."""
    import json

    import yaml

    from mmf_rl.cli import main

    _, config, _ = converted
    data = tmp_path / "slice.yaml"
    data.write_text(yaml.safe_dump(config))
    run = tmp_path / "run"
    small = ["model.d_model=16", "model.d_latent=4", "model.num_heads=2", "model.mlp_hidden=32"]
    steps = [
        "trainer.total_steps=6",
        "trainer.batch_size=16",
        "trainer.eval_every=3",
        "trainer.warmup_steps=2",
    ]
    quiet = ["trainer.progress_bar=false", "logger=csv", "num_workers=0"]
    turned = ["augment.rotation=180"]  # as the benchmark trains: the converter declared what turns
    assert main(["train", f"data={data}", f"run_dir={run}", *small, *steps, *quiet, *turned]) == 0
    assert main(["eval", f"checkpoint={run}", "num_samples=20", "plots=false"]) == 0
    scores = json.loads((run / "eval" / "results.json").read_text())["subsets"]["all"]
    # Metres: an untrained model is off by metres, not by normalised units of ~1; best of 20 <= point.
    assert 0.05 < scores["ade"] < 20.0 and scores["min_ade_k"] <= scores["ade"] + 1e-6
    assert scores["min_fde_k"] <= scores["fde"] + 1e-6


def test_heading_up_crops_show_what_lies_ahead_above_the_centre():
    scene = _coded_scene(None)
    crop = ethucy.CropConfig(pixels=33, metres=8.25, heading=True)
    centre = np.array([[5.0, 6.0]])
    # Walking east, then standing: the standing step keeps the eastward heading.
    heading = ethucy.headings(np.array([[1.2, 0.0], [0.0, 0.0]]))
    np.testing.assert_allclose(heading, [0.0, 0.0])
    image = scene.crops(centre, crop, heading[:1])[0]
    north_up = scene.crops(centre, ethucy.CropConfig(pixels=33, metres=8.25))[0]
    assert _decode(image[12, 16]) == _decode(north_up[16, 20])  # 1 m ahead (east) is 4 px up
    assert _decode(image[16, 12]) == _decode(north_up[12, 16])  # 1 m to its left (north) is 4 px left
    assert ethucy.headings(np.zeros((2, 2)))[0] == pytest.approx(np.pi / 2)  # never moved: north up


# Windows of 8 + 12 steps in each fold's test files: the sizes the literature's test sets have, every
# window (Trajectron++, AgentFormer) and those Social-GAN keeps (its published test set, one window per
# person in each of its 20-frame sequences).
TEST_WINDOWS = {
    "trajectron": {"eth": 364, "hotel": 1197, "univ": 24334, "zara1": 2356, "zara2": 5910},
    "social_gan": {"eth": 181, "hotel": 1053, "univ": 24334, "zara1": 2253, "zara2": 5833},
}


@pytest.mark.parametrize("fold", sorted(ethucy.FOLDS))
def test_each_fold_has_the_standard_number_of_test_windows_in_both_sets(fold):
    windows = {"trajectron": 0, "social_gan": 0}
    for _, path in ethucy.fold_files(RAW, fold)["test"]:
        first_frames = ethucy.track_windows(ethucy.read_sequence(path))["frame"].to_numpy()
        windows["trajectron"] += len(first_frames)
        windows["social_gan"] += int(ethucy.social_gan_windows(first_frames).sum())
    assert windows == {name: counts[fold] for name, counts in TEST_WINDOWS.items()}


def _social_gan_sequences(table: pd.DataFrame, span: int = ethucy.HISTORY + ethucy.HORIZON) -> pd.DataFrame:
    """Social-GAN's rule as its data loader states it (``sgan/data/trajectories.py``, ``skip=1``,
    ``min_ped=1``): ``span`` consecutive frames *of those the file annotates anyone in* (a frame number
    nobody has is not a step), a person counted when annotated in every one, a sequence kept with more
    than one counted; ``agent, frame`` (its first frame) per counted person of each kept sequence."""
    frames = np.unique(table["frame"])
    step = pd.Series(np.arange(len(frames)), index=frames)[table["frame"]].to_numpy()
    tracks = table.assign(step=step).sort_values(["agent", "step"])
    last = tracks.groupby("agent")["step"].shift(-(span - 1))
    counted = tracks.loc[last - tracks["step"] == span - 1, ["agent", "step"]]
    kept = counted[counted.groupby("step")["agent"].transform("size") > 1]
    return pd.DataFrame({"agent": kept["agent"].to_numpy(), "frame": frames[kept["step"].to_numpy()]})


def test_social_gan_windows_are_those_its_own_rule_gives_on_every_file():
    """Over annotated frames (the loader's) and over steps of 10 frames (the library's windows) the two
    rules agree on these files: no 20 annotated frames with two people in them span an empty frame.
    Every file, the whole ones and the _train/_val parts; one sequence per distinct first frame."""
    sequences = {}
    for path in sorted((RAW / "trajectories").glob("*/*.txt")):
        table = ethucy.read_sequence(path)
        windows = ethucy.track_windows(table)
        ours = windows[ethucy.social_gan_windows(windows["frame"].to_numpy())]
        theirs = _social_gan_sequences(table)
        assert sorted(map(tuple, ours.values.tolist())) == sorted(map(tuple, theirs.values.tolist())), path
        sequences[path.stem] = theirs["frame"].nunique()
    # Social-GAN's test sets count people: eth's 181 windows are 70 sequences of 2 people or more.
    assert {k: sequences[k] for k in ("biwi_eth", "biwi_hotel", "crowds_zara01", "crowds_zara02")} == {
        "biwi_eth": 70,
        "biwi_hotel": 301,
        "crowds_zara01": 602,
        "crowds_zara02": 921,
    }
    assert sequences["students001"] + sequences["students003"] == 947


@pytest.mark.parametrize("split", ["train", "test"])
def test_the_social_gan_windows_of_a_converted_split_are_those_of_its_file(converted, split):
    """On the eth slice (a lone pedestrian first) and on zara01 with an agent leaving for two steps."""
    root, config, info = converted
    data = WindowDataset(DataConfig.from_dict(config), num_workers=0)
    [(_, table)] = info["tables"][split]
    expected = ethucy.track_windows(table)
    expected = expected[ethucy.social_gan_windows(expected["frame"].to_numpy())]
    ids = ethucy.window_set_ids(data, split, "social_gan")
    assert 0 < len(ids) < len(data.split_windows[split])
    # Every episode is selected, so a window's first row in the cache is its global frame index.
    frames = _frames(root).sort_values("index", ignore_index=True)
    first = frames.iloc[data.window_start[ids].numpy()]
    got = np.stack([_column(first, ethucy.AGENT_KEY)[:, 0], _column(first, ethucy.FRAME_KEY)[:, 0]], 1)
    assert sorted(map(tuple, got.tolist())) == sorted(map(tuple, expected.values.tolist()))
    assert ethucy.window_set_ids(data, split, "trajectron").equal(data.split_windows[split])
    with pytest.raises(ValueError, match="unknown ETH/UCY window set 'sgan'; expected one of"):
        ethucy.window_set_ids(data, split, "sgan")


def test_raw_dims_outside_the_feature_are_refused(converted):
    _, config, _ = converted
    bad = {**config, "modalities": {**config["modalities"]}}
    bad["modalities"]["neighbours"] = {**config["modalities"]["neighbours"], "raw_dims": [4, 40]}
    with pytest.raises(
        ValueError, match=r"modalities\.neighbours\.raw_dims` \[4, 40\] must index its 40 dims"
    ):
        WindowDataset(DataConfig.from_dict(bad), num_workers=0)


def test_parts_are_sharded_in_order_by_rows():
    assert ethucy.shard_parts([10, 10, 10, 10], 2) == [range(0, 2), range(2, 4)]
    assert ethucy.shard_parts([30, 5, 5, 5, 5], 2) == [range(0, 1), range(1, 5)]
    assert ethucy.shard_parts([5, 5, 5], 1) == [range(0, 3)]
    # A part too big to share: fewer shards than workers, none empty.
    assert ethucy.shard_parts([1, 100, 1], 3) == [range(0, 1), range(1, 2), range(2, 3)]
    assert ethucy.shard_parts([1, 100], 3) == [range(0, 1), range(1, 2)]


def _convert_spied(monkeypatch, raw: Path, out: Path, workers: int | None) -> tuple[dict, list[int]]:
    """Convert fold eth; the episodes per part and the shard count of the processes' path (0: none)."""
    seen: dict = {"shards": [0]}

    def write_parts(*args):
        dataset, seen["parts"] = real_write_parts(*args)
        return dataset, seen["parts"]

    def write_shards(roots, *args):
        seen["shards"] = [len(roots)]
        return real_write_shards(roots, *args)

    real_write_parts, real_write_shards = ethucy.write_parts, ethucy._write_shards
    monkeypatch.setattr(ethucy, "write_parts", write_parts)
    monkeypatch.setattr(ethucy, "_write_shards", write_shards)
    assert ethucy.convert(raw, ["eth"], out, workers=workers) == [out / "eth.yaml"]
    assert not list(out.glob(f"{ethucy.STAGING_PREFIX}*")), "the staging dir is removed"
    return seen["parts"], seen["shards"]


@pytest.mark.slow
def test_a_conversion_in_two_processes_equals_one_in_this_process(tmp_path, monkeypatch):
    import warnings

    import yaml
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    raw = cut_ethucy_raw(tmp_path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        # The default: in this process, the cut being far too small to pay for worker processes.
        alone, no_shards = _convert_spied(monkeypatch, raw, tmp_path / "one", workers=None)
    assert not [w for w in caught if "Converting input from bool" in str(w.message)]
    shared, shards = _convert_spied(monkeypatch, raw, tmp_path / "two", workers=2)
    assert (no_shards, shards) == ([0], [2])
    assert shared == alone and list(shared) == list(alone)
    assert sum(len(e) for e in alone.values()) > 10 and alone["biwi_eth"], "parts in both shards"
    configs = [yaml.safe_load((tmp_path / n / "eth.yaml").read_text()) for n in ("one", "two")]
    assert [c.pop("root") for c in configs] == [str(tmp_path / n / "ethucy") for n in ("one", "two")]
    assert configs[0] == configs[1]
    frames = [_frames(tmp_path / n / "ethucy") for n in ("one", "two")]
    for key in ("episode_index", "frame_index", "index", "timestamp", "task_index"):
        np.testing.assert_array_equal(frames[0][key], frames[1][key], err_msg=key)
    keys = (ethucy.TRAJECTORY_KEY, ethucy.NEIGHBOURS_KEY, ethucy.AGENT_KEY, ethucy.FRAME_KEY)
    for key in (*keys, ethucy.SCENE_VALID_KEY):
        np.testing.assert_array_equal(_column(frames[0], key), _column(frames[1], key), err_msg=key)
    datasets = [LeRobotDataset("local/ethucy", root=tmp_path / n / "ethucy") for n in ("one", "two")]
    assert datasets[0].meta.tasks.equals(datasets[1].meta.tasks)
    last_part = alone["biwi_eth"]  # in the second shard, with the eth scene
    picks = [0, int(np.flatnonzero(frames[0]["episode_index"] == last_part[0])[0]), len(frames[0]) - 1]
    for index in picks:
        image = datasets[0][index][ethucy.SCENE_KEY]
        assert image.equal(datasets[1][index][ethucy.SCENE_KEY])
    assert datasets[0][picks[1]][ethucy.SCENE_KEY].any(), "a real crop, not a black frame"


def _dead_pid() -> int:
    import subprocess
    import sys

    process = subprocess.Popen([sys.executable, "-c", ""])
    process.wait()
    return process.pid


@pytest.mark.slow
@pytest.mark.parametrize("broken", ["scene image", "trajectory file"])
def test_a_broken_file_is_named_and_leaves_no_dataset(tmp_path, capsys, broken):
    from mmf_rl.cli import main
    from mmf_rl.temp_dirs import owned_temp_prefix

    raw, out = cut_ethucy_raw(tmp_path), tmp_path / "out"
    if broken == "scene image":  # read in a worker process, while converting the zara01 files
        (raw / "scenes" / "zara01").unlink()
        (raw / "scenes" / "zara01").mkdir()
        (raw / "scenes" / "zara01" / "reference.png").write_bytes(b"not a png")
        named = r"crowds_zara01_(train|val) \(\S+/crowds_zara01_\1\.txt\) failed: UnidentifiedImageError"
    else:  # read before any worker starts
        (raw / "trajectories" / "val" / "students003_val.txt").write_text("10\t1\t2.5\n")
        named = r"students003_val\.txt: expected non-empty rows of 4 numbers"
    host = owned_temp_prefix("").split("-")[1]
    stale = out / f"{ethucy.STAGING_PREFIX}{_dead_pid()}-{host}-left"
    stale.mkdir(parents=True)
    argv = ["import", "ethucy", str(raw), "--out", str(out), "--fold", "eth", "--workers", "2"]
    assert main(argv) == 1
    error = capsys.readouterr().err
    assert re.search(named, error), error
    assert not (out / ethucy.DATASET_NAME).exists() and not (out / "eth.yaml").exists()
    leftovers = list(out.glob(f"{ethucy.STAGING_PREFIX}*"))
    assert leftovers == ([] if broken == "scene image" else [stale]), "staging removed, stale ones too"


def test_the_default_starts_a_process_per_core_only_for_enough_rows_for_each(monkeypatch):
    monkeypatch.setattr(ethucy.os, "sched_getaffinity", lambda pid: {0, 1})
    rows = ethucy.MIN_ROWS_PER_WORKER
    assert [ethucy.default_workers(n) for n in (0, 1, 2 * rows - 1, 2 * rows, 100 * rows)] == [1, 1, 1, 2, 2]


def test_fewer_than_one_worker_is_refused(tmp_path):
    with pytest.raises(ValueError, match="--workers 0: expected at least 1"):
        ethucy.convert(cut_ethucy_raw(tmp_path), ["eth"], tmp_path / "out", workers=0)
    assert not (tmp_path / "out").exists()


def test_turned_windows_keep_velocities_the_steps_of_positions(converted):
    """With the converter's planar declarations, a turned window is still one walk: each velocity is
    the step between its positions, the past target is those positions from the last, neighbours
    keep their distances and validity, and the north-up crop turns with them."""
    import torch

    from mmf_rl.datasets import AugmentConfig, TrainingAugmentation
    from mmf_rl.keys import TARGET_PAST, obs_key

    _, config, _ = converted
    dataset = WindowDataset(DataConfig.from_dict(config), num_workers=0)
    augment = TrainingAugmentation(AugmentConfig.from_dict({"rotation": 180}), dataset.specs, 0)
    plain = next(iter(dataset.loader("train", 32, seed=0)))
    turned = next(iter(dataset.loader("train", 32, seed=0, augment=augment)))
    stats = dataset.normalizer.stats

    def raw(batch, name):
        return batch.get(obs_key(name)) * stats[f"{name}/std"] + stats[f"{name}/mean"]

    walk = raw(turned, "trajectory")
    positions, velocities = walk[..., :2], walk[..., 2:]
    moved = velocities[:, 1:].norm(dim=-1) > 0  # 0 where the step before was not annotated
    steps = (positions[:, 1:] - positions[:, :-1]) / ethucy.STEP_S
    assert moved.sum() > 100
    torch.testing.assert_close(steps[moved], velocities[:, 1:][moved], atol=2e-3, rtol=1e-3)
    past = dataset.normalizer.denormalize_target(turned.get(TARGET_PAST))
    torch.testing.assert_close(past, positions - positions[:, -1:], atol=2e-3, rtol=1e-3)
    slots = raw(turned, "neighbours").unflatten(-1, (8, ethucy.SLOT_DIM))
    plain_slots = raw(plain, "neighbours").unflatten(-1, (8, ethucy.SLOT_DIM))
    assert torch.equal(slots[..., 4], plain_slots[..., 4])
    torch.testing.assert_close(
        slots[..., :2].norm(dim=-1), plain_slots[..., :2].norm(dim=-1), atol=1e-3, rtol=1e-4
    )
    scene = turned.get(obs_key("scene"))
    assert config["modalities"]["scene"]["top_down"] and not torch.equal(scene, plain.get(obs_key("scene")))


@pytest.mark.slow
def test_neighbour_tracks_train_through_the_cli_with_the_slot_size_the_config_names(tmp_path):
    """`--neighbour-steps`: the data config hands the agent-slot encoder its slot size (one neighbour's
    steps), and the trained model keeps it."""
    import yaml

    from mmf_rl.cli import main
    from mmf_rl.models import load_trained_model

    neighbours = ethucy.NeighbourConfig(count=4, steps=3)
    # 30 steps of each file: 74 / 25 / 5 windows, half the conversion of the 60-step slices.
    tables = {
        "train": [("crowds_zara01", _slice("crowds_zara01", 30))],
        "val": [("crowds_zara03", _slice("crowds_zara03", 30))],
        "test": [("biwi_eth", _slice("biwi_eth", 30))],
    }
    root = tmp_path / "tracks"
    split = ethucy.write_dataset(root, tables, RAW, neighbours, ethucy.CropConfig(pixels=16))
    config = ethucy.data_config(root, split, neighbours, ethucy.CropConfig(pixels=16))
    assert config["modalities"]["neighbours"]["encoder_kwargs"] == {"slot_dim": 3 * ethucy.SLOT_DIM}
    data = tmp_path / "tracks.yaml"
    data.write_text(yaml.safe_dump(config | {"cache_dir": str(tmp_path / "cache")}))
    run = tmp_path / "run"
    small = ["model.d_model=16", "model.d_latent=4", "model.num_heads=2", "model.mlp_hidden=32"]
    steps = ["trainer.total_steps=2", "trainer.batch_size=8", "trainer.eval_every=2"]
    steps += ["trainer.warmup_steps=1"]
    quiet = ["trainer.progress_bar=false", "logger=csv", "num_workers=0", "augment.rotation=180"]
    assert main(["train", f"data={data}", f"run_dir={run}", *small, *steps, *quiet]) == 0
    model, _, _ = load_trained_model(run / "checkpoints", map_location="cpu")
    spec = next(s for s in model.config.modalities if s.name == "neighbours")
    assert spec.shape == (4 * 3 * ethucy.SLOT_DIM,) and spec.encoder_kwargs == {"slot_dim": 15}
