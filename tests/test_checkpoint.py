import json
import os
import pickle

import pytest
import torch

from mmf_rl.checkpoint import (
    CheckpointError,
    list_checkpoints,
    load_checkpoint,
    load_model_state,
    save_checkpoint,
)
from mmf_rl.models import ForecasterConfig, MultimodalForecaster


def test_roundtrip_restores_weights_tensors_and_state(tmp_path, small_model, small_config):
    stats = {"target.mean": torch.randn(2), "target.std": torch.rand(2) + 0.1}
    saved = save_checkpoint(
        tmp_path,
        100,
        small_model.state_dict(),
        meta={"config": small_config.to_dict()},
        tensors=stats,
        trainer_state={"epoch": 3, "rng": torch.get_rng_state()},
    )
    assert saved.name == "step_000000100"
    ckpt = load_checkpoint(tmp_path)  # through the `last` pointer
    assert ckpt.step == 100 and ckpt.trainer_state["epoch"] == 3
    torch.testing.assert_close(ckpt.tensors["target.std"], stats["target.std"])
    clone = MultimodalForecaster(ForecasterConfig.from_dict(ckpt.meta["config"]))
    load_model_state(clone, ckpt)
    for key, value in small_model.state_dict().items():
        assert torch.equal(clone.state_dict()[key], value)


def test_last_pointer_follows_newest_and_keep_last_prunes(tmp_path, small_model):
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, small_model.state_dict(), keep_last=2)
    assert [p.name for p in list_checkpoints(tmp_path)] == ["step_000000002", "step_000000003"]
    assert load_checkpoint(tmp_path).step == 3


def test_a_failed_write_leaves_the_previous_checkpoint_and_no_partial_one(tmp_path, small_model):
    save_checkpoint(tmp_path, 1, small_model.state_dict())

    class Unsaveable:
        def __reduce__(self):
            raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        save_checkpoint(tmp_path, 2, small_model.state_dict(), trainer_state={"x": Unsaveable()})
    assert sorted(os.listdir(tmp_path)) == ["last", "step_000000001"]
    assert load_checkpoint(tmp_path).step == 1


def test_truncated_weights_are_a_clear_error_naming_the_file(tmp_path, small_model):
    path = save_checkpoint(tmp_path, 5, small_model.state_dict())
    weights = path / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(CheckpointError, match=r"model\.safetensors.*corrupted or truncated"):
        load_checkpoint(path)


def test_pickled_code_in_trainer_state_is_refused(tmp_path, small_model):
    path = save_checkpoint(tmp_path, 5, small_model.state_dict(), trainer_state={"ok": 1})

    class RunsCode:
        def __reduce__(self):
            return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

    with open(path / "trainer_state.pt", "wb") as f:
        pickle.dump({"payload": RunsCode()}, f)
    with pytest.raises(CheckpointError, match="refusing to load"):
        load_checkpoint(path)
    assert not (tmp_path / "pwned").exists()


def test_checkpoint_of_another_model_config_names_the_mismatch(tmp_path, small_model, small_config):
    path = save_checkpoint(tmp_path, 5, small_model.state_dict())
    other = MultimodalForecaster(ForecasterConfig.from_dict({**small_config.to_dict(), "d_latent": 6}))
    with pytest.raises(
        CheckpointError, match=r"different model configuration.*shape mismatch.*expected \[.*\], found \["
    ):
        load_model_state(other, load_checkpoint(path))


def test_missing_and_non_checkpoint_paths(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope")
    with pytest.raises(CheckpointError, match="neither a checkpoint"):
        load_checkpoint(tmp_path)
    bad = tmp_path / "step_000000001"
    bad.mkdir()
    (bad / "meta.json").write_text(json.dumps({"hello": 1}))
    with pytest.raises(CheckpointError, match="not an mmf-rl checkpoint"):
        load_checkpoint(bad)
