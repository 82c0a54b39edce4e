import pytest
import torch
from torch import nn

from mmf_rl import keys
from mmf_rl.keys import DEFAULT_ENCODER, ModalitySpec
from mmf_rl.models import ForecasterConfig, build_model, encoders, model_from_saved_config, saved_config
from mmf_rl.models.encoders import ENCODERS, build_encoder, encoders_for, register_encoder
from tests.conftest import HISTORY, HORIZON, SMALL_MODALITIES, TARGET_DIM, make_batch


def test_every_default_encoder_is_registered_for_its_kind():
    for kind, name in DEFAULT_ENCODER.items():
        assert kind in ENCODERS[name].kinds


@pytest.mark.parametrize("model_name", ["forecaster", "lf_lstm", "mvae", "mult"])
def test_an_encoder_not_registered_for_the_kind_fails_when_the_model_is_built(model_name):
    specs = [ModalitySpec("x", "vector", (3,), encoder="gru")]
    with pytest.raises(ValueError) as err:
        build_model({"name": model_name}, specs, HISTORY, HORIZON, TARGET_DIM)
    message = str(err.value)
    assert "modality 'x' (vector): encoder 'gru' is not available" in message and "['mlp']" in message


def test_an_unknown_encoder_names_how_to_register_one():
    spec = ModalitySpec("cam", "image", (3, 16, 16), encoder="resnet")
    with pytest.raises(
        ValueError,
        match=r"expected one of \['conv', 'conv_frames', 'conv_gru', 'conv_patches'\].*register_encoder",
    ):
        ForecasterConfig(modalities=[spec])


def test_bad_encoder_kwargs_are_a_clear_error():
    spec = ModalitySpec("f", "sequence", (6,), encoder_kwargs={"channels": (4,)})
    with pytest.raises(ValueError, match=r"modality 'f': bad encoder_kwargs \{'channels': \(4,\)\} for"):
        build_encoder(spec, HISTORY, 8)


@pytest.mark.parametrize("model_name", ["lf_lstm", "mult"])
def test_bad_encoder_kwargs_of_a_baselines_per_frame_convnet_are_a_clear_error(model_name):
    specs = [ModalitySpec("cam", "image", (3, 16, 16), encoder_kwargs={"slot_dim": 3})]
    with pytest.raises(
        ValueError, match=r"modality 'cam': bad encoder_kwargs \{'slot_dim': 3\} for the baselines'"
    ):
        build_model({"name": model_name}, specs, HISTORY, HORIZON, TARGET_DIM)


def test_an_image_encoder_without_convolutions_is_a_clear_error():
    spec = ModalitySpec("cam", "image", (3, 16, 16), encoder_kwargs={"channels": ()})
    with pytest.raises(ValueError, match=r"image encoder for 'cam': channels is empty"):
        build_encoder(spec, HISTORY, 8)


def test_registration_refuses_a_taken_name_and_unknown_kinds(monkeypatch):
    monkeypatch.setattr(encoders, "ENCODERS", dict(ENCODERS))
    with pytest.raises(ValueError, match="encoder 'gru' is already registered"):
        register_encoder("gru", kinds=("sequence",))(lambda spec, history, d_model: nn.Identity())
    with pytest.raises(ValueError, match="kinds must be a non-empty subset"):
        register_encoder("audio_cnn", kinds=("audio",))


class LastStepEncoder(nn.Module):
    """A user's encoder: a linear map of the window's last step."""

    def __init__(self, in_dim: int, d_model: int):
        super().__init__()
        self.project = nn.Linear(in_dim, d_model)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        return self.project(seq[:, -1])


def test_one_registration_makes_a_new_encoder_usable_end_to_end(monkeypatch):
    monkeypatch.setattr(encoders, "ENCODERS", dict(ENCODERS))  # the registration ends with the test

    @register_encoder("last_step", kinds=("sequence",))
    def last_step(spec, history, d_model):
        return LastStepEncoder(spec.shape[0], d_model)

    assert "last_step" in encoders_for("sequence") and "last_step" not in encoders_for("image")
    specs = [
        s if s.name != "force" else ModalitySpec("force", "sequence", (6,), encoder="last_step")
        for s in SMALL_MODALITIES
    ]
    model = build_model(
        {
            "name": "forecaster",
            "d_model": 16,
            "d_latent": 4,
            "num_heads": 2,
            "mlp_hidden": 32,
            "head_hidden": 32,
        },
        specs,
        HISTORY,
        HORIZON,
        TARGET_DIM,
    )
    assert isinstance(model.encoders["force"], LastStepEncoder)
    out = model.train()(make_batch(8, modalities=specs))
    assert out.get(keys.FORECAST_LOC).shape == (8, HORIZON, TARGET_DIM)
    out.get(keys.FORECAST_LOC).sum().backward()
    assert model.encoders["force"].project.weight.grad.abs().sum() > 0
    # A checkpoint's model_config names it, so the same registration rebuilds the model.
    rebuilt = model_from_saved_config(saved_config("forecaster", model))
    assert isinstance(rebuilt.encoders["force"], LastStepEncoder)
