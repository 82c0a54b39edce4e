"""Models by name, so configs, checkpoints and benchmarks build any of them the same way.

An entry gives the model's config class, its module class, and the losses it trains with. Every
model reads the same batch contract (mmf_rl.keys) and writes ``("forecast", "loc"/"scale")``;
models with a latent also write ``("posterior", ...)``. Baselines register here beside the
paper's forecaster.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from torch import nn

from mmf_rl.checkpoint import CheckpointError, load_checkpoint, load_model_state
from mmf_rl.keys import ModalitySpec
from mmf_rl.models.baselines import MVAE, LateFusionLSTM, LFLSTMConfig, MulT, MulTConfig, MVAEConfig
from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster
from mmf_rl.objectives import CombinedLoss, ELBOLoss, GaussianNLLLoss, LossConfig, MissingModalityLoss


@dataclass(frozen=True)
class ModelEntry:
    config_cls: type
    model_cls: type
    make_loss: Callable[[nn.Module, LossConfig], nn.Module]


def forecaster_loss(model: MultimodalForecaster, loss_cfg: LossConfig) -> CombinedLoss:
    """ELBO, plus the missing-modality loss unless its weight is 0 (the paper's ablation)."""
    losses = [ELBOLoss(model, kl_weight=loss_cfg.kl_weight, kl_warmup_steps=loss_cfg.kl_warmup_steps,
                       gsnn_weight=loss_cfg.gsnn_weight)]
    if loss_cfg.missing_modality_weight > 0:
        losses.append(MissingModalityLoss(model, weight=loss_cfg.missing_modality_weight,
                                          detach_teacher=loss_cfg.detach_teacher, max_dropped=loss_cfg.max_dropped,
                                          dropped_nll_weight=loss_cfg.dropped_nll_weight,
                                          prior_weight=loss_cfg.dropped_prior_weight))
    return CombinedLoss(*losses)


def nll_loss(model: nn.Module, loss_cfg: LossConfig) -> GaussianNLLLoss:
    """Deterministic baselines: the Gaussian NLL of the future (the loss config has no term for them)."""
    return GaussianNLLLoss(model)


def mvae_loss(model: MVAE, loss_cfg: LossConfig) -> ELBOLoss:
    """The MVAE's ELBO with the loss config's KL weight and warm-up; it has no missing-modality term."""
    if loss_cfg.gsnn_weight > 0:
        raise ValueError("loss.gsnn_weight > 0 needs a model that decodes from its prior in training "
                         "(model=forecaster); the MVAE baseline does not: set loss.gsnn_weight=0")
    return ELBOLoss(model, kl_weight=loss_cfg.kl_weight, kl_warmup_steps=loss_cfg.kl_warmup_steps)


MODELS: dict[str, ModelEntry] = {
    "forecaster": ModelEntry(ForecasterConfig, MultimodalForecaster, forecaster_loss),
    "lf_lstm": ModelEntry(LFLSTMConfig, LateFusionLSTM, nll_loss),
    "mvae": ModelEntry(MVAEConfig, MVAE, mvae_loss),
    "mult": ModelEntry(MulTConfig, MulT, nll_loss),
}


def _entry(name: str) -> ModelEntry:
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; expected one of {sorted(MODELS)}")
    return MODELS[name]


def build_model(model_cfg: dict, modalities: list[ModalitySpec], history: int, horizon: int,
                target_dim: int, action_shape: tuple[int, int] | None = None) -> nn.Module:
    """``model_cfg`` is the model config group (its ``name`` picks the entry); the data fixes the rest.

    ``action_shape = (S, A)`` (the data config sets ``action``) builds an action-conditioned world
    model; only the paper's forecaster has that option.
    """
    cfg = dict(model_cfg)
    name = cfg.pop("name", "forecaster")
    entry = _entry(name)
    fields = {**cfg, "modalities": modalities, "history": history, "horizon": horizon, "target_dim": target_dim}
    if action_shape is not None:
        if entry.config_cls is not ForecasterConfig:
            raise ValueError(
                f"model {name!r} has no action input, but the data config sets `action` (a world model); "
                "use model=forecaster, or remove `action` from the data config"
            )
        fields.update(action_steps=action_shape[0], action_dim=action_shape[1])
    return entry.model_cls(entry.config_cls.from_dict(fields))


def model_from_saved_config(saved: dict) -> nn.Module:
    """Rebuild a model from the ``model_config`` a checkpoint stores (see :func:`saved_config`)."""
    cfg = dict(saved)
    entry = _entry(cfg.pop("name", "forecaster"))
    return entry.model_cls(entry.config_cls.from_dict(cfg))


def load_trained_model(path, map_location="cpu") -> tuple[nn.Module, dict, dict]:
    """A trained model from a checkpoint (``path``: a checkpoint, or a run's ``checkpoints/``):
    the model with its weights in eval mode, its normalisation stats, and the run's data config."""
    checkpoint = load_checkpoint(path, with_trainer_state=False)
    if "model_config" not in checkpoint.meta:
        raise CheckpointError(f"{checkpoint.path} has no 'model_config' in its meta.json; it was not written by "
                              "`mmf-rl train` (or save_checkpoint(meta={'model_config': saved_config(...)}))")
    model = model_from_saved_config(checkpoint.meta["model_config"])
    load_model_state(model, checkpoint)
    data_config = checkpoint.meta.get("config", {}).get("data", {})
    return model.to(map_location).eval(), checkpoint.tensors, data_config


def saved_config(name: str, model: nn.Module) -> dict:
    """What a checkpoint stores to rebuild ``model``: its registry name and full config."""
    return {"name": name, **model.config.to_dict()}


def build_loss(name: str, model: nn.Module, loss_cfg: LossConfig) -> nn.Module:
    """The losses model ``name`` trains with, weighted by the loss config group."""
    return _entry(name).make_loss(model, loss_cfg)
