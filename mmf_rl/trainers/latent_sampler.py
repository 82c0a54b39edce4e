"""The second stage of a run whose model has a learned sampler: train it on the frozen forecaster.

``mmf-rl train model.learned_samples=20 sampler.steps=1500 ...`` trains the forecaster, then the sampler
(:mod:`mmf_rl.models.latent_sampler`) on the same training windows, turned and augmented as the
forecaster's were, with :class:`~mmf_rl.objectives.DiverseSamplingLoss`; then calibration, and the
last checkpoint and ``run_dir/model`` carry both. The forecaster's weights do not change: its point
forecasts are those of the same run without a sampler.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.objectives import DiverseSamplingLoss
from mmf_rl.trainers.trainer import Trainer, TrainerConfig, seed_everything

logger = logging.getLogger(__name__)


@dataclass
class SamplerConfig:
    """How the learned sampler trains (``mmf-rl train``'s ``sampler`` settings); read only when the model
    has ``learned_samples > 0``, which needs ``steps > 0``.

    Args:
        steps (int, optional): optimizer updates of the sampler (0, the default: no sampler to train).
        batch_size (int, optional): windows per update; each is decoded ``K`` times. Defaults to ``64``.
        lr (float, optional): Adam's peak learning rate (cosine decay to zero over ``steps``). Defaults to
            ``1e-3``.
        best_of_k_weight (float, optional): :class:`~mmf_rl.objectives.DiverseSamplingLoss`'s. Defaults
            to ``5.0``.
        diversity_weight (float, optional): its. Defaults to ``5.0``.
        diversity_scale (float, optional): its, in the target's squared units. Defaults to ``5.0``.
        kl_weight (float, optional): its. Defaults to ``0.1``.
        kl_floor (float, optional): its. Defaults to ``10.0``.
        drop_prob (float, optional): its. Defaults to ``0.5``.

    Raises:
        ValueError: ``steps`` or ``batch_size`` not a whole number (``steps >= 0``, ``batch_size >= 1``).
    """

    steps: int = 0
    batch_size: int = 64
    lr: float = 1e-3
    best_of_k_weight: float = 5.0
    diversity_weight: float = 5.0
    diversity_scale: float = 5.0
    kl_weight: float = 0.1
    kl_floor: float = 10.0
    drop_prob: float = 0.5

    def __post_init__(self):
        for name in ("steps", "batch_size"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int)
                or value < (1 if name == "batch_size" else 0)
            ):
                raise ValueError(
                    f"sampler.{name} must be a whole number >= {int(name == 'batch_size')}, found {value!r}"
                )

    @classmethod
    def from_dict(cls, d: dict | None) -> SamplerConfig:
        reject_unknown_keys(cls, d or {}, "sampler config")
        return cls(**(d or {}))


def check_sampler_settings(learned_samples: int, config: SamplerConfig) -> None:
    """A model with a learned sampler needs steps to train it; steps without a sampler would train nothing."""
    if learned_samples and not config.steps:
        raise ValueError(
            f"model.learned_samples={learned_samples} builds a learned sampler that sampler.steps=0 leaves "
            "untrained; set sampler.steps (e.g. sampler.steps=1500) or model.learned_samples=0"
        )
    if config.steps and not learned_samples:
        raise ValueError(
            f"sampler.steps={config.steps} trains a learned sampler, but the model has none; set "
            "model.learned_samples=K (e.g. 20) or sampler.steps=0"
        )


def train_latent_sampler(model, data, config: SamplerConfig, augment=None, seed: int = 0) -> str:
    """Train ``model.latent_sampler`` on ``data``'s train split with the rest of ``model`` frozen; the
    message saying what was done. ``augment``: the forecaster's training augmentation."""
    loss = DiverseSamplingLoss(
        model,
        target_scale=data.normalizer.stats["target/std"],
        best_of_k_weight=config.best_of_k_weight,
        diversity_weight=config.diversity_weight,
        diversity_scale=config.diversity_scale,
        kl_weight=config.kl_weight,
        kl_floor=config.kl_floor,
        drop_prob=config.drop_prob,
    ).to(next(model.parameters()).device)
    trainer_cfg = TrainerConfig(
        total_steps=config.steps,
        batch_size=config.batch_size,
        lr=config.lr,
        warmup_steps=min(50, config.steps // 10),
        log_every=max(1, config.steps // 10),
        eval_every=config.steps,
        checkpoint_every=config.steps,
        seed=seed,
        progress_bar=False,
    )
    trainable = {p: p.requires_grad for p in model.parameters()}
    model.requires_grad_(False).latent_sampler.requires_grad_(True)
    seed_everything(seed)
    loader = data.loader("train", config.batch_size, seed=seed, augment=augment)
    try:
        trainer = Trainer(model.latent_sampler, loss, loader, trainer_cfg)
        trainer.train()
    finally:
        for parameter, requires_grad in trainable.items():
            parameter.requires_grad_(requires_grad)
        model.eval()
    last = trainer.history[-1] if trainer.history else {}
    terms = ", ".join(
        f"{k.removeprefix('train/')}={v:.4g}" for k, v in last.items() if k.startswith("train/loss_")
    )
    return (
        f"learned sampler ({model.latent_sampler.num_samples} codes) trained {trainer.step} steps ({terms})"
    )
