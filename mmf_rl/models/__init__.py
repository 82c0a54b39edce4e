from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster
from mmf_rl.models.hub import PretrainedModel
from mmf_rl.models.registry import (
    MODELS,
    TrainedModelSource,
    build_loss,
    build_model,
    from_pretrained,
    init_weights_from,
    load_trained_model,
    locate_trained_model,
    model_config_with_overrides,
    model_from_saved_config,
    saved_config,
)

__all__ = [
    "MODELS",
    "ForecasterConfig",
    "MultimodalForecaster",
    "PretrainedModel",
    "TrainedModelSource",
    "build_loss",
    "build_model",
    "from_pretrained",
    "init_weights_from",
    "load_trained_model",
    "locate_trained_model",
    "model_config_with_overrides",
    "model_from_saved_config",
    "saved_config",
]
