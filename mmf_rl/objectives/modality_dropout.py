"""Modality dropout: training batches with sensors removed, drawn afresh at every batch, for any model.

The paper model learns to forecast without a sensor through ``L_mis``; a model without that term
(LF-LSTM, MVAE, MulT) only learns it if its supervised term sees inputs with sensors missing. This
module removes modalities from each training batch's ``("present", m)`` masks before the loss runs,
so every term of any registered model (NLL, ELBO, ``L_mis``) trains on the reduced input. With
``L_mis`` as well, its teacher is the reduced input and its student drops further from it.

A fixed set of windows without a sensor (``data.missing``) shows a model the same gaps every epoch;
a draw per batch shows each window under many presence patterns over a run.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDict, TensorDictBase

from mmf_rl.objectives.common import ForecasterLossBase
from mmf_rl.objectives.config import check_rate

SUBSETS = "subsets"
OBSERVED = "observed"  # resolved to rates by whoever has the data: the training windows' absences


def uniform_nonempty_subsets(present: torch.Tensor) -> torch.Tensor:
    """``[B, M]`` bool: for each row, a subset of its present modalities drawn uniformly among the
    non-empty ones (the full set included). Rows without a present modality stay empty."""
    # Keeping each present modality with probability 1/2 is uniform over all subsets; redrawing the
    # rows that came out empty makes it uniform over the non-empty ones.
    kept = present & (torch.rand(present.shape, device=present.device) < 0.5)
    while (redraw := present.any(1) & ~kept.any(1)).any():
        fresh = present & (torch.rand(present.shape, device=present.device) < 0.5)
        kept = torch.where(redraw.unsqueeze(1), fresh, kept)
    return kept


def drop_at_rates(present: torch.Tensor, rates: torch.Tensor) -> torch.Tensor:
    """``[B, M]`` bool: each present modality removed independently with its rate ``[M]``; a row left
    with nothing keeps one of its present modalities, drawn uniformly."""
    kept = present & (torch.rand(present.shape, device=present.device) >= rates)
    emptied = present.any(1) & ~kept.any(1)
    scores = torch.rand(present.shape, device=present.device).masked_fill(~present, -1.0)
    one = torch.nn.functional.one_hot(scores.argmax(1), present.shape[1]).bool()
    return torch.where(emptied.unsqueeze(1), one, kept)


class ModalityDropout(ForecasterLossBase):
    """A loss whose training batches have modalities removed at random, drawn anew at every batch.

    Wraps the model's loss (one term or a :class:`~mmf_rl.objectives.CombinedLoss`): :meth:`prepare`
    rewrites the batch's ``("present", m)`` masks, then hands it to the wrapped loss's own
    ``prepare``, forward pass and terms. A modality absent from a sample stays absent; a sample never
    loses its last present modality. Draws use the global torch RNG, so seeded runs repeat.

    Two presence distributions:

    * ``subsets`` (``rates=None``): with probability ``subset_prob`` a sample keeps a subset of its
      present modalities drawn uniformly among the non-empty ones (the full set included), so every
      presence pattern a test can ask for is trained, single sensors as often as pairs;
    * ``rates={m: p}``: each modality is removed independently with its own probability (a modality
      not named: never), e.g. the data's own observed absence rates (``loss.modality_dropout=observed``).

    Args:
        loss (ForecasterLossBase): the wrapped forecaster loss.

    Keyword Args:
        subset_prob (float, optional): ``subsets``' share of samples redrawn, in ``(0, 1]``.
        rates (Mapping[str, float], optional): per modality of the forecaster, its removal probability in
            ``[0, 1)``.

    Give exactly one of ``subset_prob`` and ``rates``. Calling it on a batch returns the wrapped loss's
    entries plus ``dropout_fraction``, the share of samples that lost at least one modality to the
    dropout.

    Raises:
        ValueError: both or neither of ``subset_prob`` and ``rates``, ``subset_prob`` outside
            ``(0, 1]``, or ``rates`` naming a modality the forecaster lacks or a rate outside ``[0, 1)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> from mmf_rl.objectives import GaussianNLLLoss, ModalityDropout
        >>> model = MultimodalForecaster(ForecasterConfig(
        ...     modalities=[ModalitySpec("force", "sequence", (6,)), ModalitySpec("pose", "vector", (3,))],
        ...     history=4, horizon=5, target_dim=2, d_model=16, d_latent=4, num_heads=2,
        ... ))
        >>> batch = TensorDict({
        ...     ("obs", "force"): torch.randn(8, 4, 6), ("present", "force"): torch.ones(8, dtype=torch.bool),
        ...     ("obs", "pose"): torch.randn(8, 3), ("present", "pose"): torch.ones(8, dtype=torch.bool),
        ...     "target": torch.randn(8, 5, 2),
        ... }, batch_size=[8])
        >>> torch.manual_seed(1)  # the draws use the global RNG
        <torch._C.Generator object at ...>
        >>> loss = ModalityDropout(GaussianNLLLoss(model), rates={"force": 0.5})
        >>> out = loss(batch)
        >>> sorted(out.keys())
        ['dropout_fraction', 'loss_nll']
        >>> out["dropout_fraction"]  # the share of samples that trained without the force
        tensor(0.5000)
    """

    def __init__(
        self,
        loss: ForecasterLossBase,
        *,
        subset_prob: float | None = None,
        rates: Mapping[str, float] | None = None,
    ):
        super().__init__(loss.forecaster)
        self.loss = loss
        self.modality_names = [spec.name for spec in loss.forecaster.modalities]
        if (subset_prob is None) == (rates is None):
            raise ValueError("ModalityDropout takes exactly one of subset_prob (subsets) and rates ({m: p})")
        if subset_prob is not None and not 0 < subset_prob <= 1:
            raise ValueError(f"subset_prob must be in (0, 1], found {subset_prob}")
        self.subset_prob = subset_prob
        self.rates = None if rates is None else check_rates(rates, self.modality_names)
        self._fraction = torch.zeros(())

    @property
    def in_keys(self) -> list:
        return self.loss.in_keys

    @property
    def out_keys(self) -> list:
        return [*self.loss.out_keys, "dropout_fraction"]

    def _loss_in_keys(self) -> list:
        return self.loss._loss_in_keys()

    def kept(self, present: torch.Tensor) -> torch.Tensor:
        """The modalities each sample keeps of its ``present`` ones (a fresh draw).

        Args:
            present (torch.Tensor): ``bool [B, M]``, the forecaster's modalities in order.

        Returns:
            ``bool [B, M]``, within ``present``, with at least one per row that had one.
        """
        if self.rates is not None:
            rates = torch.tensor([self.rates.get(m, 0.0) for m in self.modality_names], device=present.device)
            return drop_at_rates(present, rates)
        redrawn = torch.rand(present.shape[0], device=present.device) < self.subset_prob
        return torch.where(redrawn.unsqueeze(1), uniform_nonempty_subsets(present), present)

    def prepare(self, td: TensorDictBase) -> TensorDictBase:
        specs = self.forecaster.modalities
        present = torch.stack([td.get(spec.present_key) for spec in specs], dim=1)
        kept = self.kept(present)
        for i, spec in enumerate(specs):
            td.set(spec.present_key, kept[:, i])
        # Not a batch entry (a scalar), so kept here until the terms are computed.
        self._fraction = (kept != present).any(1).float().mean()
        return self.loss.prepare(td)

    def loss_from_outputs(self, td: TensorDictBase) -> TensorDict:
        out = self.loss.loss_from_outputs(td)
        out.set("dropout_fraction", self._fraction)
        return out


def with_modality_dropout(loss: ForecasterLossBase, loss_cfg) -> ForecasterLossBase:
    """``loss`` wrapped in the :class:`ModalityDropout` that ``loss_cfg.modality_dropout`` asks for (as
    it is without one). ``observed`` must have been resolved to rates first
    (:func:`resolve_observed_dropout`): only the data knows them."""
    choice = loss_cfg.modality_dropout
    if choice is None:
        return loss
    if choice == OBSERVED:
        raise ValueError(
            "loss.modality_dropout=observed needs the training data's absence rates; resolve it with "
            "resolve_observed_dropout(loss_cfg, absent_fraction) before building the loss"
        )
    if choice == SUBSETS:
        return ModalityDropout(loss, subset_prob=loss_cfg.modality_dropout_prob)
    return ModalityDropout(loss, rates=choice)


def resolve_observed_dropout(loss_cfg, absent_fraction: Mapping[str, float]):
    """Resolve ``modality_dropout=observed`` to the training data's absence rates.

    Args:
        loss_cfg (LossConfig): the loss config.
        absent_fraction (Mapping[str, float]): each modality's share of absent frames in the training
            split (the ``fraction`` of ``WindowDataset.observed_outages``).

    Returns:
        ``loss_cfg`` with ``modality_dropout`` set to the nonzero rates (a new config); any other
        config as it is.

    Raises:
        ValueError: no modality is ever absent (a rate of 0 everywhere would train nothing new).
    """
    if loss_cfg.modality_dropout != OBSERVED:
        return loss_cfg
    rates = {name: float(fraction) for name, fraction in absent_fraction.items() if fraction > 0}
    if not rates:
        raise ValueError(
            "loss.modality_dropout=observed: no modality is ever absent in the training split, so there "
            "is nothing to replay; use loss.modality_dropout=subsets or give rates {modality: p}"
        )
    return dataclasses.replace(loss_cfg, modality_dropout=rates)


def check_rates(rates: Mapping[str, float], modality_names: Sequence[str]) -> dict[str, float]:
    """``rates`` as a plain dict, refused (naming the fix) if a name is not a modality or a rate is not
    in ``[0, 1)``."""
    unknown = sorted(set(rates) - set(modality_names))
    if unknown:
        raise ValueError(
            f"loss.modality_dropout names {unknown}, which are not modalities of the model; expected names "
            f"among {list(modality_names)}"
        )
    for name, rate in rates.items():
        check_rate(name, rate)
    return {name: float(rate) for name, rate in rates.items()}
