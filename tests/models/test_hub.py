"""save_pretrained / from_pretrained (huggingface_hub's PyTorchModelHubMixin) from a local directory."""

import json

import pytest
import torch

from mmf_rl import keys
from mmf_rl.checkpoint import CheckpointError
from mmf_rl.models import MODELS, from_pretrained
from mmf_rl.models.baselines import LateFusionLSTM
from tests.conftest import HISTORY, HORIZON, make_batch, small_registered_model


@pytest.mark.parametrize("name", sorted(MODELS))
def test_local_round_trip_gives_the_same_forecasts(name, tmp_path):
    model = small_registered_model(name)
    model.normalization_stats = {
        "target/mean": torch.tensor([1.0, 2.0]),
        "target/std": torch.tensor([0.5, 3.0]),
    }
    model.data_config = {"history": HISTORY, "horizon": HORIZON, "stride": 2}
    model.save_pretrained(tmp_path / "saved")
    files = {p.name for p in (tmp_path / "saved").iterdir()}
    assert files == {
        "config.json",
        "model.safetensors",
        "normalization.safetensors",
        "data_config.json",
        "README.md",
    }
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "no temporary directory left behind"
    assert json.loads((tmp_path / "saved" / "config.json").read_text())["name"] == name

    reloaded = type(model).from_pretrained(tmp_path / "saved")
    generic = from_pretrained(tmp_path / "saved")
    batch = make_batch(6, present={"image": torch.tensor([True, False] * 3)}, seed=4)
    expected = model(batch.clone()).get(keys.FORECAST_LOC)
    for loaded in (reloaded, generic):
        assert type(loaded) is type(model) and not loaded.training
        assert torch.equal(loaded(batch.clone()).get(keys.FORECAST_LOC), expected)
        assert torch.equal(loaded.normalization_stats["target/std"], torch.tensor([0.5, 3.0]))
        assert loaded.data_config == {"history": HISTORY, "horizon": HORIZON, "stride": 2}


def test_loading_is_strict_and_names_what_does_not_fit(tmp_path):
    small_registered_model("forecaster").save_pretrained(tmp_path / "saved")
    with pytest.raises(TypeError, match=r"holds a 'forecaster' model .* not a LateFusionLSTM"):
        LateFusionLSTM.from_pretrained(tmp_path / "saved")
    config = json.loads((tmp_path / "saved" / "config.json").read_text())
    config["d_latent"] = 6
    (tmp_path / "saved" / "config.json").write_text(json.dumps(config))
    fit = r"model.safetensors does not fit this model .*posterior_head.2.bias: expected \[12\], found \[8\]"
    with pytest.raises(CheckpointError, match=fit):
        from_pretrained(tmp_path / "saved")
    (tmp_path / "saved" / "model.safetensors").unlink()
    with pytest.raises(
        FileNotFoundError, match=r"not a saved mmf-rl model: .*model.safetensors does not exist"
    ):
        from_pretrained(tmp_path / "saved")
