"""Missingness protocols: seeded training dropout and the fixed evaluation subsets."""

import warnings

import pytest
import torch
from tensordict import TensorDict

from mmf_rl.datasets.config import DataConfig
from mmf_rl.datasets.protocols import (
    apply_presence_subset,
    outage_statistics,
    presence_subsets,
    replayed_outage_frames,
    training_dropout,
)
from mmf_rl.datasets.windows import WindowDataset
from mmf_rl.keys import ModalitySpec, obs_key, present_key, validate_batch
from tests.datasets.conftest import NAN_FORCE_EPISODE, synthetic_config


def test_training_dropout_is_seeded_and_exact():
    n = 200
    present = {name: torch.ones(n, dtype=torch.bool) for name in ("image", "force", "proprio")}
    a = training_dropout(present, {"image": 0.3}, seed=5)
    b = training_dropout(present, {"image": 0.3}, seed=5)
    c = training_dropout(present, {"image": 0.3}, seed=6)
    assert torch.equal(a["image"], b["image"]) and not torch.equal(a["image"], c["image"])
    assert int((~a["image"]).sum()) == 60 and a["force"].all()
    # Adding a modality to the protocol does not move the samples chosen for another.
    both = training_dropout(present, {"image": 0.3, "force": 0.5}, seed=5)
    assert torch.equal(both["image"], a["image"]) and int((~both["force"]).sum()) == 100


def test_training_dropout_never_leaves_a_sample_empty():
    present = {
        "image": torch.tensor([True, True, True, True]),
        "force": torch.tensor([False, True, False, True]),
    }
    out = training_dropout(present, {"image": 1.0}, seed=0)
    assert torch.equal(out["image"], torch.tensor([True, False, True, False]))
    assert (out["image"] | out["force"]).all()


def test_dataset_applies_protocol_to_train_windows_only(synthetic_root, tmp_path):
    def open_with(seed):
        config = synthetic_config(synthetic_root, tmp_path, missing={"image": 0.5}, missing_seed=seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return WindowDataset(config)

    dataset = open_with(11)
    train = dataset.split_windows["train"]
    dropped = dataset.presence["image"][train] & ~dataset.train_presence["image"][train]
    assert int(dropped.sum()) == round(0.5 * len(train))  # state is always present: nothing restored
    assert torch.equal(open_with(11).train_presence["image"], dataset.train_presence["image"])
    assert not torch.equal(open_with(12).train_presence["image"], dataset.train_presence["image"])
    for split in ("val", "test"):
        ids = dataset.split_windows[split]
        assert torch.equal(dataset.train_presence["image"][ids], dataset.presence["image"][ids])
        assert torch.equal(
            dataset.batch(ids, split).get(present_key("image")), dataset.presence["image"][ids]
        )
    assert torch.equal(
        dataset.batch(train, "train").get(present_key("image")), dataset.train_presence["image"][train]
    )
    assert dataset.config.to_dict()["missing"] == {"image": 0.5}


def test_presence_subsets_names_and_application():
    subsets = dict(presence_subsets(["image", "force", "proprio"]))
    assert list(subsets) == [
        "all",
        "without_image",
        "without_force",
        "without_proprio",
        "only_image",
        "only_force",
        "only_proprio",
    ]
    assert subsets["without_force"] == {"image": True, "force": False, "proprio": True}
    assert list(dict(presence_subsets(["a", "b"]))) == ["all", "without_a", "without_b"]
    assert list(dict(presence_subsets(["a"]))) == ["all"]

    batch = TensorDict(
        {
            "obs": {"image": torch.zeros(3, 2, 3, 4, 4, dtype=torch.uint8), "force": torch.ones(3, 2, 6)},
            "present": {
                "image": torch.tensor([True, False, True]),
                "force": torch.tensor([True, True, False]),
            },
            "target": torch.zeros(3, 5, 2),
        },
        batch_size=[3],
    )
    only_image = apply_presence_subset(batch, {"image": True, "force": False})
    assert only_image.batch_size[0] == 2  # the sample whose camera was missing has nothing left
    assert not only_image.get(present_key("force")).any()
    assert batch.get(present_key("force")).tolist() == [True, True, False], "the input batch was modified"
    assert only_image.get(obs_key("force")).shape == (2, 2, 6)
    validate_batch(
        only_image, [ModalitySpec("image", "image", (3, 4, 4)), ModalitySpec("force", "sequence", (6,))], 2
    )


# --- outages: measured, replayed ---------------------------------------------------------------


def test_outage_statistics_cut_runs_at_episode_ends():
    present = torch.tensor([1, 0, 0, 1, 0, 0, 0, 1, 0], dtype=torch.bool)
    episode = torch.tensor([0, 0, 0, 0, 0, 1, 1, 1, 1])
    # absent runs: [1, 2] and [4] in episode 0, [5, 6] and [8] in episode 1
    assert outage_statistics(present, episode) == {
        "fraction": 6 / 9,
        "outages": 4,
        "mean_burst": 1.5,
        "max_burst": 2,
    }
    assert outage_statistics(torch.ones(4, dtype=torch.bool), torch.zeros(4))["outages"] == 0


def test_replayed_outages_have_the_measured_statistics():
    n, fraction, mean_burst = 100_000, 0.1, 8.0
    absent = replayed_outage_frames(n, fraction, mean_burst, torch.Generator().manual_seed(0))
    stats = outage_statistics(~absent, torch.zeros(n, dtype=torch.long))
    assert abs(stats["fraction"] - fraction) < 0.01 and abs(stats["mean_burst"] - mean_burst) < 0.5
    again = replayed_outage_frames(n, fraction, mean_burst, torch.Generator().manual_seed(0))
    assert torch.equal(absent, again)


def test_dataset_replays_outages_on_train_windows(synthetic_root, tmp_path):
    def open_with(missing):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return WindowDataset(synthetic_config(synthetic_root, tmp_path, missing=missing))

    plain = open_with({})
    train = plain.split_windows["train"]
    observed = plain.observed_outages
    nan_force_in_train = NAN_FORCE_EPISODE in plain.split_episodes["train"]
    assert observed["force"]["outages"] == int(nan_force_in_train) and observed["state"]["fraction"] == 0.0
    assert observed["force"]["mean_burst"] == (5.0 if nan_force_in_train else 0.0)
    replayed = open_with({"force": {"fraction": 0.3, "mean_burst": 3}})
    lost = plain.presence["force"][train] & ~replayed.train_presence["force"][train]
    assert (
        lost.any() and not (replayed.train_presence["force"][train] & ~plain.presence["force"][train]).any()
    )
    for split in ("val", "test"):
        ids = plain.split_windows[split]
        assert torch.equal(replayed.train_presence["force"][ids], plain.presence["force"][ids])
    assert torch.equal(replayed.train_presence["image"], plain.presence["image"])
    assert replayed.config.to_dict()["missing"] == {"force": {"fraction": 0.3, "mean_burst": 3.0}}
    # "observed" replays what the training split shows: here the camera's and the force's spans.
    measured = open_with("observed")
    assert measured.observed_outages == observed
    changed = {
        name
        for name in plain.presence
        if not torch.equal(measured.train_presence[name], plain.presence[name])
    }
    assert changed == {name for name, o in observed.items() if 0 < o["fraction"] < 1}


def test_missing_config_errors_name_the_key():
    d = {"modalities": {"force": "observation.force"}, "target": "observation.state"}
    with pytest.raises(ValueError, match=r"`missing` must be a mapping .* or 'observed', found 'seen'"):
        DataConfig.from_dict({**d, "missing": "seen"})
    with pytest.raises(ValueError, match=r"missing\.force: unknown keys \['mean'\]"):
        DataConfig.from_dict({**d, "missing": {"force": {"fraction": 0.1, "mean": 3}}})
    with pytest.raises(ValueError, match=r"0 <= fraction < 1 and mean_burst >= 1"):
        DataConfig.from_dict({**d, "missing": {"force": {"fraction": 0.1, "mean_burst": 0.5}}})
