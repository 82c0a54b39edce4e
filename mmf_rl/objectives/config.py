"""The loss config group (``configs/loss/*.yaml``): the weights of the forecaster's training terms."""

from __future__ import annotations

from dataclasses import dataclass

from mmf_rl.configuration import reject_unknown_keys


@dataclass
class LossConfig:
    """How a model's losses are weighted; each model's registry entry picks the terms it uses.

    The defaults are the losses' own (β = 1 without warm-up, ``L_mis`` at weight 1 with a detached
    teacher); a training run takes its values from ``configs/loss/<name>.yaml``.

    Args:
        kl_weight: ``β`` of the ELBO's KL term once warm (:class:`~mmf_rl.objectives.ELBOLoss`).
        kl_warmup_steps: training updates over which ``β`` grows linearly to ``kl_weight`` (0: constant).
        missing_modality_weight: weight of ``L_mis`` (:class:`~mmf_rl.objectives.MissingModalityLoss`);
            0 trains without it (the paper's ablation, ``loss=no_mis``).
        detach_teacher: stop the gradient through ``L_mis``'s full-modality side.
    """

    kl_weight: float = 1.0
    kl_warmup_steps: int = 0
    missing_modality_weight: float = 1.0
    detach_teacher: bool = True

    def __post_init__(self):
        for name in ("kl_weight", "kl_warmup_steps", "missing_modality_weight"):
            if getattr(self, name) < 0:
                raise ValueError(f"loss.{name} must be >= 0, found {getattr(self, name)}")
        if not isinstance(self.detach_teacher, bool):
            raise ValueError(f"loss.detach_teacher must be true or false, found {self.detach_teacher!r}")

    @classmethod
    def from_dict(cls, d: dict) -> LossConfig:
        reject_unknown_keys(cls, d, "loss config")
        return cls(**d)
