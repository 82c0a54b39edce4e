from mmf_rl.models.baselines import MVAE, LateFusionLSTM, MulT
from mmf_rl.models.finetune import init_weights_from
from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster
from mmf_rl.models.hub import PretrainedModel
from mmf_rl.models.loading import (
    RUN_EXPORT_DIR,
    TRAINED_MODEL_KINDS,
    TrainedModelSource,
    from_pretrained,
    load_trained_model,
    locate_trained_model,
)
from mmf_rl.models.registry import (
    MODELS,
    build_loss,
    build_model,
    check_loss_settings,
    loss_settings_read,
    model_config_with_overrides,
    model_entry,
    model_from_saved_config,
    register_model,
    saved_config,
    trained_loss_terms,
)

__all__ = [
    "MODELS",
    "MVAE",
    "RUN_EXPORT_DIR",
    "TRAINED_MODEL_KINDS",
    "ForecasterConfig",
    "LateFusionLSTM",
    "MulT",
    "MultimodalForecaster",
    "PretrainedModel",
    "TrainedModelSource",
    "build_loss",
    "build_model",
    "check_loss_settings",
    "from_pretrained",
    "init_weights_from",
    "load_trained_model",
    "locate_trained_model",
    "loss_settings_read",
    "model_config_with_overrides",
    "model_entry",
    "model_from_saved_config",
    "register_model",
    "saved_config",
    "trained_loss_terms",
]
