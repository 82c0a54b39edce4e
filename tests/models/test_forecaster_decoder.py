"""The forecaster's decoder options: MulT's pair streams as its input (``decoder_input="pair_streams"``)
and how ``z`` enters it (``decoder_latent``)."""

import dataclasses
import json

import pytest
import torch

from mmf_rl import keys
from mmf_rl.cli import main as cli
from mmf_rl.models import MultimodalForecaster, build_loss, from_pretrained
from mmf_rl.models.loading import load_trained_model
from mmf_rl.objectives import LossConfig
from tests.conftest import (
    HISTORY,
    HORIZON,
    SMALL_MODALITIES,
    assert_a_few_steps_reduce_the_loss,
    assert_each_sample_alone_gives_its_batch_result,
    assert_forecast_under_actions_is_one_forward_per_candidate,
    make_batch,
    push_train_overrides,
)

STEP_MODALITIES = [
    dataclasses.replace(s, encoder="steps") if s.kind != "image" else s for s in SMALL_MODALITIES
]
LATENTS = ["joint", "linear", "none"]
OUTPUTS = [keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.POSTERIOR_LOC, keys.POSTERIOR_SCALE]
ACTION_SHAPE = (HORIZON, 3)


def build(small_config, modalities=SMALL_MODALITIES, **changes) -> MultimodalForecaster:
    torch.manual_seed(0)
    return MultimodalForecaster(dataclasses.replace(small_config, modalities=list(modalities), **changes))


def mixed(modalities, mixed_batch, seed: int = 1):
    """A batch of ``modalities`` with the presence patterns of ``mixed_batch`` (one sample per pattern)."""
    batch = make_batch(mixed_batch.shape[0], modalities, seed=seed)
    for spec in modalities:
        batch.set(spec.present_key, mixed_batch.get(spec.present_key))
    return batch


def with_trailing_absent_steps(batch, modalities):
    """``("present_steps", m)`` where windows lose their last steps (sample ``b`` loses ``b % 3``), so a
    pair's query is not the last token."""
    for spec in modalities:
        steps = torch.ones(batch.shape[0], HISTORY, dtype=torch.bool)
        for b in range(batch.shape[0]):
            steps[b, HISTORY - b % 3 :] = False
        batch.set(keys.present_steps_key(spec.name), steps)
    return batch


def garbled(batch, modalities):
    """``batch`` with huge values under every absent modality and absent step."""
    out = batch.clone()
    for spec in modalities:
        obs = out.get(spec.obs_key)
        steps = out.get(keys.present_steps_key(spec.name), None)
        absent = ~out.get(spec.present_key).view(-1, 1).expand(-1, HISTORY)
        absent = absent if steps is None else absent | ~steps
        obs[absent] = (255 if spec.kind == "image" else 1e6) - obs[absent]
    return out


@pytest.mark.parametrize(
    "modalities, latent, pair_self",
    [
        (SMALL_MODALITIES, "linear", "always"),
        (STEP_MODALITIES, "joint", "always"),
        (STEP_MODALITIES, "none", "always"),
        (STEP_MODALITIES, "linear", "alone"),
    ],
    ids=["window-linear", "steps-joint", "steps-none", "steps-linear-self-alone"],
)
def test_pair_streams_keep_the_presence_invariants_when_windows_end_absent(
    small_config, mixed_batch, modalities, latent, pair_self
):
    """Output shapes, a mixed batch giving each sample its own result, and nothing stored under an
    absent modality or step changing any output, when windows lose their last steps (the pair
    queries move; tests/models/test_tokens.py covers windows that end present)."""
    model = build(
        small_config, modalities, decoder_input="pair_streams", decoder_latent=latent, pair_self=pair_self
    ).eval()
    batch = with_trailing_absent_steps(mixed(modalities, mixed_batch), modalities)
    with torch.no_grad():
        reference = model(batch.clone())
        out = model(garbled(batch, modalities))
    assert reference.get(keys.FORECAST_LOC).shape == (batch.shape[0], HORIZON, 2)
    for key in OUTPUTS:
        assert torch.equal(out.get(key), reference.get(key)), key
    assert_each_sample_alone_gives_its_batch_result(model, batch, OUTPUTS)


def test_trailing_absent_steps_move_the_query_to_the_last_present_step(small_config, batch):
    """With per-step tokens, a window that loses its last step is read at the step before: its
    readouts are those of the pair layers queried there."""
    model = build(small_config, STEP_MODALITIES, decoder_input="pair_streams").eval()
    steps = torch.ones(batch.shape[0], HISTORY, dtype=torch.bool)
    steps[:, -1] = False
    partial = batch.clone()
    partial.set(keys.present_steps_key("force"), steps)
    with torch.no_grad():
        tokens, present = model.encode(partial)
        readouts = model.decoder_tokens(tokens, present)
        force = slice(1, 1 + HISTORY)  # image (one token), then force's steps
        pair = model.pair_streams.pairs.index((1, 1))
        stream = model.pair_streams.layers[pair](tokens[:, force], tokens[:, force], ~present[:, force])
    torch.testing.assert_close(readouts[:, pair], stream[:, -2])
    assert not torch.allclose(readouts[:, pair], stream[:, -1])


@pytest.mark.parametrize("decoder_input", ["pair_streams", "mixed_pair_streams"])
@pytest.mark.parametrize("modalities", [SMALL_MODALITIES, STEP_MODALITIES], ids=["window", "steps"])
def test_a_dropped_modality_makes_its_pairs_absent_for_the_student(
    small_config, mixed_batch, modalities, decoder_input
):
    """``L_mis``'s student decodes without the dropped modality's pairs: what a decode with that
    modality absent gives, from the same tokens and ``z`` (over mixed tokens, mixed without it)."""
    model = build(small_config, modalities, decoder_input=decoder_input).train()
    td = mixed(modalities, mixed_batch)
    names = [s.name for s in modalities]
    present = torch.stack([td.get(keys.present_key(n)) for n in names], 1)
    drop = torch.zeros_like(present)
    multi = present.sum(1) >= 2
    drop[multi, present[multi].float().argmax(1)] = True  # the first present modality
    for i, name in enumerate(names):
        td.set(keys.drop_key(name), drop[:, i])
    out = model(td)
    tokens, token_present = model.encode(td)
    kept = token_present & ~drop[:, model.token_modality]
    z = out.get(keys.LATENT)
    teacher, student = model.decode(tokens, token_present, z)[0], model.decode(tokens, kept, z)[0]
    torch.testing.assert_close(out.get(keys.FORECAST_LOC), teacher, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(out.get(keys.FORECAST_DROPPED_LOC), student, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(teacher[multi], student[multi])
    i, j = model.pair_streams.pair_modality, model.pair_streams.pair_source
    assert bool(model.decoder_layout(kept)[0][drop[:, i] | drop[:, j]].all())


@pytest.mark.parametrize("latent", LATENTS)
@pytest.mark.parametrize("decoder_input", ["tokens", "mixed", "pair_streams", "mixed_pair_streams"])
def test_the_decoder_reads_z_unless_decoder_latent_is_none(small_config, batch, decoder_input, latent):
    model = build(small_config, decoder_input=decoder_input, decoder_latent=latent).eval()
    tokens, present = model.encode(batch)
    z = torch.randn(batch.shape[0], small_config.d_latent, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        same = torch.equal(model.decode(tokens, present, z)[0], model.decode(tokens, present, z + 1)[0])
    assert same is (latent == "none")


def test_each_decoder_latent_builds_only_what_it_uses(small_config):
    d, d_z = small_config.d_model, small_config.d_latent

    def decoder_parts(**changes):
        state = build(small_config, **changes).state_dict()
        return {
            k.split(".")[1]: v.shape for k, v in state.items() if k.endswith(".weight") and "decoder." in k
        }

    assert "joint" in decoder_parts() and "condition" not in decoder_parts()
    assert "joint" not in decoder_parts(decoder_latent="linear")
    assert decoder_parts(decoder_latent="linear")["condition"] == (d, d_z)
    assert not {"joint", "condition"} & set(decoder_parts(decoder_latent="none"))
    world = {"action_steps": ACTION_SHAPE[0], "action_dim": ACTION_SHAPE[1]}
    assert decoder_parts(decoder_latent="none", **world)["condition"] == (d, d)  # the actions alone


@pytest.mark.parametrize(
    "decoder_input, latent",
    [("mixed", "none"), ("pair_streams", "joint"), ("pair_streams", "linear"), ("pair_streams", "none")],
)
def test_a_world_model_plans_with_each_decoder_option(small_config, mixed_batch, decoder_input, latent):
    """``forecast_under_actions`` is one forward per candidate, and the actions move the forecast even
    when ``z`` does not enter."""
    model = build(
        small_config,
        decoder_input=decoder_input,
        decoder_latent=latent,
        action_steps=ACTION_SHAPE[0],
        action_dim=ACTION_SHAPE[1],
    ).eval()
    actions = torch.randn(mixed_batch.shape[0], 3, *ACTION_SHAPE, generator=torch.Generator().manual_seed(5))
    loc, _ = assert_forecast_under_actions_is_one_forward_per_candidate(model, mixed_batch, actions)
    assert (loc[:, 0] - loc[:, 1]).abs().amax(dim=(1, 2)).min() > 1e-6


def test_unknown_decoder_options_are_clear_errors(small_config):
    unknown_input = r"decoder_input must be one of .*'mixed_pair_streams'\), found 'pairs'"
    with pytest.raises(ValueError, match=unknown_input):
        dataclasses.replace(small_config, decoder_input="pairs")
    with pytest.raises(ValueError, match=r"decoder_latent must be one of \('joint', 'linear', 'none'\)"):
        dataclasses.replace(small_config, decoder_latent="additive")


def test_a_model_saved_before_the_options_loads_unchanged(small_config, batch, tmp_path):
    """The defaults build no pair layers and no linear map, and a saved config without
    ``decoder_latent`` loads as the joint MLP with the same forecasts."""
    model = build(small_config).eval()
    assert not [k for k in model.state_dict() if k.startswith("pair_streams.") or ".condition." in k]
    model.save_pretrained(tmp_path / "saved")
    config_file = tmp_path / "saved" / "config.json"
    saved = json.loads(config_file.read_text())
    del saved["decoder_latent"]
    config_file.write_text(json.dumps(saved))
    loaded = from_pretrained(tmp_path / "saved")
    assert loaded.config.decoder_latent == "joint"
    with torch.no_grad():
        assert torch.equal(
            loaded(batch.clone()).get(keys.FORECAST_LOC), model(batch.clone()).get(keys.FORECAST_LOC)
        )


@pytest.mark.parametrize("latent", ["joint", "none"])
def test_a_pair_stream_model_round_trips(small_config, tmp_path, latent):
    model = build(small_config, STEP_MODALITIES, decoder_input="pair_streams", decoder_latent=latent).eval()
    model.save_pretrained(tmp_path / "saved")
    loaded = from_pretrained(tmp_path / "saved")
    assert loaded.config == model.config
    steps_batch = make_batch(6, STEP_MODALITIES, present={"image": torch.tensor([True, False] * 3)})
    with torch.no_grad():
        expected = model(steps_batch.clone()).get(keys.FORECAST_LOC)
        assert torch.equal(loaded(steps_batch.clone()).get(keys.FORECAST_LOC), expected)


def test_a_pair_stream_model_trains(small_config):
    model = build(
        small_config, STEP_MODALITIES, decoder_input="pair_streams", decoder_latent="linear"
    ).train()
    assert_a_few_steps_reduce_the_loss(model, build_loss("forecaster", model, LossConfig()))


def test_pair_streams_train_and_evaluate_on_recorded_push_data(recorded_push_root, tmp_path):
    """`mmf-rl train` then `mmf-rl eval` on real push data, with the benchmark entry's options."""
    run = tmp_path / "run"
    options = [
        "model.decoder_input=pair_streams",
        "model.decoder_latent=linear",
        "data.modalities.force.encoder=steps",
        "data.modalities.proprio.encoder=steps",
        "data.partial_windows=true",
    ]
    overrides = push_train_overrides(recorded_push_root, tmp_path / "cache", run, steps=3)
    assert cli(["train", *overrides, *options]) == 0
    model, _, _ = load_trained_model(run)
    assert (model.config.decoder_input, model.config.decoder_latent) == ("pair_streams", "linear")
    assert cli(["eval", f"checkpoint={run}", "num_samples=2", "plots=false"]) == 0


class EvalForecast(torch.nn.Module):
    """``forecast_from_tokens`` as a module, what ``torch.jit.trace`` takes (as `mmf_rl.rl` traces it)."""

    def __init__(self, model: MultimodalForecaster):
        super().__init__()
        self.model = model

    def forward(self, tokens: torch.Tensor, present: torch.Tensor):
        return self.model.forecast_from_tokens(tokens, present)


# The tracer warns of the Python branches on shapes (attention checks, the number of draws).
@pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning")
def test_one_trace_of_the_pair_stream_forecast_serves_every_presence_pattern(small_config, mixed_batch):
    """No Python branch on presence values: a trace made with every token present gives the eager
    forecast for mixed modalities and windows that end absent."""
    model = build(small_config, STEP_MODALITIES, decoder_input="pair_streams").eval()
    batch = with_trailing_absent_steps(mixed(STEP_MODALITIES, mixed_batch), STEP_MODALITIES)
    with torch.no_grad():
        tokens, present = model.encode(batch)
        traced = torch.jit.trace(EvalForecast(model), (tokens, torch.ones_like(present)), check_trace=False)
        torch.testing.assert_close(traced(tokens, present), model.forecast_from_tokens(tokens, present))


def test_alone_self_pairs_act_only_on_a_lone_modality(small_config, batch):
    """With ``pair_self="alone"`` the self-pair layers change no forecast while two or more modalities
    are present, and do change a lone modality's."""
    model = build(small_config, STEP_MODALITIES, decoder_input="pair_streams", pair_self="alone").eval()
    lone = batch.clone()
    for spec in STEP_MODALITIES[1:]:
        lone.set(spec.present_key, torch.zeros_like(lone.get(spec.present_key)))
    with torch.no_grad():
        before = [model(b.clone()).get(keys.FORECAST_LOC) for b in (batch, lone)]
        for k, (i, j) in enumerate(model.pair_streams.pairs):
            if i == j:
                for p in model.pair_streams.layers[k].parameters():
                    p.add_(torch.randn_like(p))
        after = [model(b.clone()).get(keys.FORECAST_LOC) for b in (batch, lone)]
    assert torch.equal(after[0], before[0])
    assert not torch.allclose(after[1], before[1])
