"""The loss config group (``configs/loss/*.yaml``): the weights of the forecaster's training terms."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from mmf_rl.configuration import compose_config, reject_unknown_keys, to_container

# Where L_mis's step cuts fall in a window: its last steps, or a run of steps anywhere.
STEP_CUTS = ("tail", "burst")
# `modality_dropout`'s named distributions (a mapping {modality: rate} is the third form).
DROPOUT_CHOICES = (None, "subsets", "observed")


def check_count(value, label: str, null: str | None = None) -> None:
    """Raise a ValueError naming ``label`` unless ``value`` is a whole number >= 1 (a bool is not one),
    or ``None`` where ``null`` (the words after "or null", maybe none) allows it."""
    if value is None and null is not None:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        allowed = "" if null is None else f" or null{null}"
        raise ValueError(f"{label} must be a whole number >= 1{allowed}, found {value!r}")


def check_rate(modality: str, rate) -> None:
    """Raise a ValueError naming ``loss.modality_dropout.<modality>`` unless ``rate`` is in ``[0, 1)``."""
    if isinstance(rate, bool) or not isinstance(rate, int | float) or not 0 <= rate < 1:
        raise ValueError(f"loss.modality_dropout.{modality} must be a rate in [0, 1), found {rate!r}")


@dataclass
class LossConfig:
    """How a model's losses are weighted; each model's registry entry picks the terms it uses
    (``@register_model(..., loss=...)``) unless ``terms`` names others.

    The defaults are the losses' own (β = 1 without warm-up, ``L_mis`` at weight 1, trained end to
    end as the paper does); a training run takes its values from ``configs/loss/<name>.yaml``. Each
    term reads some of the settings (its ``config_fields``), some only under a condition (its
    ``unread_settings``: e.g. ``best_of_k_samples`` only with ``best_of_k_weight > 0``): one changed
    from its default that none of the run's terms reads is refused (``check_settings_read``);
    ``terms``, which chooses the terms, is exempt.

    Args:
        kl_weight (float, optional): ``β`` of the ELBO's KL term once warm
            (:class:`~mmf_rl.objectives.ELBOLoss`).
        kl_warmup_steps (int, optional): training updates over which ``β`` grows linearly to ``kl_weight`` (0:
            constant).
        missing_modality_weight (float, optional): weight of ``L_mis``
            (:class:`~mmf_rl.objectives.MissingModalityLoss`); 0 trains without it (the paper's ablation,
            ``loss=no_mis``).
        detach_teacher (bool, optional): stop the gradient through ``L_mis``'s full-modality side.
        gsnn_weight (float, optional): > 0 also decodes from ``z ~ p(z|X)`` in training and adds that NLL with
            this weight (Sohn et al.'s GSNN term); models without a prior decode refuse it.
        best_of_k_weight (float, optional): > 0 also decodes ``best_of_k_samples`` draws ``z ~ p(z|X)`` per
            window in training and adds this weight times the MSE of the closest one to the target
            (Bhattacharyya et al.'s best-of-many term); models without a prior decode refuse it.
        best_of_k_samples (int, optional): ``K``, the draws of that term (20: the minADE20 / minFDE20 of
            ETH/UCY).
        max_dropped (int, optional): ``L_mis`` drops ``k ~ U{1..min(max_dropped, M_i - 1)}`` present
            modalities per sample; 1 is the paper's setting, ``None`` up to ``M_i - 1`` (single-modality
            inputs trained).
        dropped_nll_weight (float, optional): > 0 adds the target's NLL under the degraded forecast beside
            ``L_mis``.
        dropped_prior_weight (float, optional): learned prior only: weight of ``KL(p(z|X) || p(z|X without the
            dropped))``.
        step_drop_prob (float, optional): probability that ``L_mis`` cuts the last steps of one windowed
            modality of a sample instead of dropping whole modalities (a sensor dying mid-window); 0: never.
        max_dropped_steps (int, optional): the most steps such a tail cut removes; ``None``: all but one
            present step.
        step_cut (str, optional): where those steps are: ``"tail"``, the last ones (a sensor dying);
            ``"burst"``, a run of consecutive present steps anywhere in the window (a sensor dropping out and
            back).
        terms (list[str], optional): the loss terms to train with, by registered name
            (``mmf_rl.objectives.LOSS_TERMS``, ``@register_loss_term``); null: the model's own.
        modality_dropout (str | dict[str, float], optional): remove modalities from each training batch, drawn
            anew every batch, before every term (:class:`~mmf_rl.objectives.ModalityDropout`; any model): null
            (off), ``"subsets"`` (a share ``modality_dropout_prob`` of the samples keeps a uniformly drawn
            non-empty subset of its modalities), ``{modality: rate}`` (each removed with its rate) or
            ``"observed"`` (those rates measured in the training split's own absences).
        modality_dropout_prob (float, optional): the share of samples ``"subsets"`` redraws, in ``(0, 1]``.

    Raises:
        ValueError: a negative weight, a count below 1, a probability out of range, an unknown
            ``step_cut`` or ``modality_dropout``, an empty ``terms``, or ``modality_dropout_prob`` set
            without ``modality_dropout="subsets"``; the message names the ``loss.`` key.

    Examples:
        >>> from mmf_rl.objectives import LossConfig
        >>> LossConfig(kl_warmup_steps=500, modality_dropout="subsets").missing_modality_weight
        1.0
        >>> LossConfig.from_dict({"kl_weigth": 0.5})
        Traceback (most recent call last):
            ...
        ValueError: loss config: unknown keys ['kl_weigth']; expected a subset of [...]
    """

    kl_weight: float = 1.0
    kl_warmup_steps: int = 0
    missing_modality_weight: float = 1.0
    detach_teacher: bool = False
    gsnn_weight: float = 0.0
    best_of_k_weight: float = 0.0
    best_of_k_samples: int = 20
    max_dropped: int | None = 1
    dropped_nll_weight: float = 0.0
    dropped_prior_weight: float = 1.0
    step_drop_prob: float = 0.0
    max_dropped_steps: int | None = None
    step_cut: str = "tail"
    terms: list[str] | None = None
    modality_dropout: str | dict[str, float] | None = None
    modality_dropout_prob: float = 0.5

    def __post_init__(self):
        self._check_modality_dropout()
        check_count(self.max_dropped, "loss.max_dropped", null="")
        check_count(self.max_dropped_steps, "loss.max_dropped_steps", null=" (all but one present step)")
        check_count(self.best_of_k_samples, "loss.best_of_k_samples")
        if not 0 <= self.step_drop_prob <= 1:
            raise ValueError(f"loss.step_drop_prob must be in [0, 1], found {self.step_drop_prob}")
        if self.step_cut not in STEP_CUTS:
            raise ValueError(f"loss.step_cut must be one of {list(STEP_CUTS)}, found {self.step_cut!r}")
        for name in (
            "kl_weight",
            "kl_warmup_steps",
            "missing_modality_weight",
            "gsnn_weight",
            "best_of_k_weight",
            "dropped_nll_weight",
            "dropped_prior_weight",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"loss.{name} must be >= 0, found {getattr(self, name)}")
        if self.terms is not None:
            if (
                isinstance(self.terms, str)
                or not all(isinstance(t, str) for t in self.terms)
                or not self.terms
            ):
                raise ValueError(
                    f"loss.terms must be a non-empty list of loss term names or null, found {self.terms!r}"
                )
            self.terms = list(self.terms)
        if not isinstance(self.detach_teacher, bool):
            raise ValueError(f"loss.detach_teacher must be true or false, found {self.detach_teacher!r}")

    def _check_modality_dropout(self) -> None:
        choice = self.modality_dropout
        if isinstance(choice, Mapping):
            self.modality_dropout = dict(choice)
            for name, rate in choice.items():
                check_rate(name, rate)
        elif choice not in DROPOUT_CHOICES:
            raise ValueError(
                f"loss.modality_dropout must be null, {' or '.join(map(repr, DROPOUT_CHOICES[1:]))} or a "
                f"mapping {{modality: rate}}, found {choice!r}"
            )
        if not 0 < self.modality_dropout_prob <= 1:
            raise ValueError(
                f"loss.modality_dropout_prob must be in (0, 1], found {self.modality_dropout_prob}"
            )
        if self.modality_dropout != "subsets" and self.modality_dropout_prob != 0.5:
            raise ValueError(
                f"loss.modality_dropout_prob={self.modality_dropout_prob} is read only with "
                f"loss.modality_dropout=subsets (found {choice!r}); set that or remove it"
            )

    @classmethod
    def from_dict(cls, d: dict) -> LossConfig:
        """Build from plain data (the Hydra ``loss`` config).

        Args:
            d (dict): the settings.

        Returns:
            The config.

        Raises:
            ValueError: an unknown key or an invalid value.
        """
        reject_unknown_keys(cls, d, "loss config")
        return cls(**d)


def default_loss_config(config_dirs=()) -> LossConfig:
    """The loss settings ``mmf-rl train`` composes when none is chosen (``configs/train.yaml``'s loss
    option, ``configs/loss/default.yaml``): what a run gets without asking, e.g. the ELBO's KL warm-up,
    which a model trained without the ELBO gets too.

    Args:
        config_dirs (Sequence[Path], optional): more config directories, as ``--config-dir``.

    Returns:
        The composed loss config.
    """
    return LossConfig.from_dict(to_container(compose_config("train", [], list(config_dirs)).loss))
