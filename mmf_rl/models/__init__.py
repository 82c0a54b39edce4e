from mmf_rl.models.forecaster import ForecasterConfig, MultimodalForecaster

__all__ = ["ForecasterConfig", "MultimodalForecaster"]
