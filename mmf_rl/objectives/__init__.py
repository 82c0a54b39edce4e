from mmf_rl.objectives.combined import CombinedLoss
from mmf_rl.objectives.common import (
    ForecasterLossBase,
    gaussian_kl,
    gaussian_kl_to_standard,
    gaussian_nll,
    model_settings_of,
)
from mmf_rl.objectives.config import LossConfig, default_loss_config
from mmf_rl.objectives.distributions import (
    OUTPUT_DISTRIBUTIONS,
    LaplaceOutput,
    NormalOutput,
    OutputDistribution,
    StudentTOutput,
    output_distribution,
    output_distribution_of,
    register_output_distribution,
)
from mmf_rl.objectives.diverse_sampling import DiverseSamplingLoss
from mmf_rl.objectives.elbo import ELBOLoss
from mmf_rl.objectives.missing_modality import MissingModalityLoss
from mmf_rl.objectives.modality_dropout import ModalityDropout, resolve_observed_dropout
from mmf_rl.objectives.nll import GaussianNLLLoss
from mmf_rl.objectives.registry import (
    GLOBAL_LOSS_SETTINGS,
    LOSS_TERMS,
    build_loss_terms,
    check_settings_read,
    loss_term,
    register_loss_term,
    settings_read,
    terms_reading,
)

__all__ = [
    "CombinedLoss",
    "DiverseSamplingLoss",
    "ELBOLoss",
    "ForecasterLossBase",
    "GLOBAL_LOSS_SETTINGS",
    "GaussianNLLLoss",
    "LOSS_TERMS",
    "LaplaceOutput",
    "LossConfig",
    "MissingModalityLoss",
    "ModalityDropout",
    "NormalOutput",
    "OUTPUT_DISTRIBUTIONS",
    "OutputDistribution",
    "StudentTOutput",
    "build_loss_terms",
    "check_settings_read",
    "default_loss_config",
    "gaussian_kl",
    "gaussian_kl_to_standard",
    "gaussian_nll",
    "loss_term",
    "model_settings_of",
    "output_distribution",
    "output_distribution_of",
    "register_loss_term",
    "register_output_distribution",
    "resolve_observed_dropout",
    "settings_read",
    "terms_reading",
]
