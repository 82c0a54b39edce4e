from mmf_rl.models.forecaster.configuration_forecaster import ForecasterConfig
from mmf_rl.models.forecaster.modeling_forecaster import MultimodalForecaster

__all__ = ["ForecasterConfig", "MultimodalForecaster"]
