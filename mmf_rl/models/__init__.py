from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster
from mmf_rl.models.registry import (
    MODELS,
    build_loss,
    build_model,
    load_trained_model,
    model_from_saved_config,
    saved_config,
)

__all__ = ["MODELS", "ForecasterConfig", "MultimodalForecaster", "build_loss", "build_model", "load_trained_model",
           "model_from_saved_config", "saved_config"]
