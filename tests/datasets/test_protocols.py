"""Missingness protocols: seeded training dropout and the fixed evaluation subsets."""

import warnings

import torch
from tensordict import TensorDict

from mmf_rl.datasets.protocols import apply_presence_subset, presence_subsets, training_dropout
from mmf_rl.datasets.windows import WindowDataset
from mmf_rl.keys import ModalitySpec, obs_key, present_key, validate_batch
from tests.datasets.conftest import synthetic_config


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
    present = {"image": torch.tensor([True, True, True, True]), "force": torch.tensor([False, True, False, True])}
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
        assert torch.equal(dataset.batch(ids, split).get(present_key("image")), dataset.presence["image"][ids])
    assert torch.equal(dataset.batch(train, "train").get(present_key("image")), dataset.train_presence["image"][train])
    assert dataset.config.to_dict()["missing"] == {"image": 0.5}


def test_presence_subsets_names_and_application():
    subsets = dict(presence_subsets(["image", "force", "proprio"]))
    assert list(subsets) == ["all", "without_image", "without_force", "without_proprio",
                             "only_image", "only_force", "only_proprio"]
    assert subsets["without_force"] == {"image": True, "force": False, "proprio": True}
    assert list(dict(presence_subsets(["a", "b"]))) == ["all", "without_a", "without_b"]
    assert list(dict(presence_subsets(["a"]))) == ["all"]

    batch = TensorDict({
        "obs": {"image": torch.zeros(3, 2, 3, 4, 4, dtype=torch.uint8), "force": torch.ones(3, 2, 6)},
        "present": {"image": torch.tensor([True, False, True]), "force": torch.tensor([True, True, False])},
        "target": torch.zeros(3, 5, 2),
    }, batch_size=[3])
    only_image = apply_presence_subset(batch, {"image": True, "force": False})
    assert only_image.batch_size[0] == 2  # the sample whose camera was missing has nothing left
    assert not only_image.get(present_key("force")).any()
    assert batch.get(present_key("force")).tolist() == [True, True, False], "the input batch was modified"
    assert only_image.get(obs_key("force")).shape == (2, 2, 6)
    validate_batch(only_image, [ModalitySpec("image", "image", (3, 4, 4)), ModalitySpec("force", "sequence", (6,))], 2)
