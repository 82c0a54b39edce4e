"""An action-conditioned forecaster with its normalisation: raw actions in, target units out."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.datasets.splits import Normalizer
from mmf_rl.models.forecaster import MultimodalForecaster
from mmf_rl.models.loading import load_trained_model
from mmf_rl.models.rows import compute_on_rows
from mmf_rl.objectives import output_distribution_of
from mmf_rl.rl.transforms import RUN_STATS_FIX, HistoryWindow, require_stats, trained_per_step_presence


class WorldModel:
    """A trained world model (a `MultimodalForecaster` with ``action_dim > 0``) ready to plan with.

    Splits the forward in two so a planner pays for the encoders once per decision and for the
    decoder once per batch of candidates: :meth:`encode` a history window, then
    :meth:`forecast` it under any number of raw action sequences (:meth:`forecast_distribution`: with
    the forecast's standard deviation too). Forecasts are in the target's units (for the push data:
    the object's planar displacement from now, metres).

    A window row with no present modality (NaN/Inf readings count as absent) cannot be encoded;
    its forecasts are the target's training mean (the marginal, as `ForecastTransform` does),
    whatever the actions.

    Action dims the training data never varied (std at the data config's ``std_floor``, e.g.
    FetchPush's finger command) are read as their training value whatever a planner asks: the
    model knows nothing about changing them, and normalising by the floor would blow a small
    change up into an input thousands of stds away.

    A trained run's: ``WorldModel.from_checkpoint("runs/world_model")``.

    Args:
        model (MultimodalForecaster): an action-conditioned forecaster (``action_dim > 0``); put in
            eval mode.
        stats (Mapping[str, torch.Tensor]): its training run's normalisation statistics, with
            ``"future_action/mean"`` and ``"future_action/std"``.
        stride (int, optional): its data's stride (its history window's). Defaults to ``1``.
        std_floor (float, optional): its data config's ``std_floor``: an action dim whose std is at it
            never varied in training. Defaults to ``1e-3``.
        per_step_presence (bool, optional): its history window's presence rule (the run's
            ``data.partial_windows``). Defaults to ``False``.

    Raises:
        ValueError: a model without action input.
        KeyError: ``stats`` lacks the action's statistics.

    Examples:
        >>> import torch
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> proprio = ModalitySpec("proprio", "sequence", (17,))
        >>> sizes = dict(history=4, horizon=5, d_model=16, d_latent=4, num_heads=2)
        >>> sizes.update(action_dim=4, action_steps=5)  # the push env's actions over the 5 steps
        >>> model = MultimodalForecaster(ForecasterConfig([force, proprio], **sizes))  # untrained world model
        >>> stats = {  # its training run's normalisation statistics (a checkpoint's tensors)
        ...     "force/mean": torch.zeros(6), "force/std": torch.ones(6),
        ...     "proprio/mean": torch.zeros(17), "proprio/std": torch.ones(17),
        ...     "target/mean": torch.zeros(2), "target/std": torch.ones(2),
        ...     "future_action/mean": torch.zeros(4), "future_action/std": torch.ones(4),
        ... }
        >>> from tensordict import TensorDict
        >>> from mmf_rl.rl import WorldModel
        >>> world_model = WorldModel(model, stats)
        >>> window = TensorDict({  # two history windows, as HistoryWindow writes them
        ...     ("obs", "force"): torch.randn(2, 4, 6),
        ...     ("present", "force"): torch.tensor([True, False]),
        ...     ("obs", "proprio"): torch.randn(2, 4, 17),
        ...     ("present", "proprio"): torch.ones(2, dtype=torch.bool),
        ... }, batch_size=[2])
        >>> encoded = world_model.encode(window)  # once per decision
        >>> candidates = torch.rand(2, 64, 5, 4) * 2 - 1  # 64 raw action sequences per window
        >>> world_model.forecast(*encoded, candidates).shape  # [n, N, T, D], target units
        torch.Size([2, 64, 5, 2])
    """

    def __init__(
        self,
        model: MultimodalForecaster,
        stats: Mapping[str, torch.Tensor],
        stride: int = 1,
        std_floor: float = 1e-3,
        per_step_presence: bool = False,
    ):
        if not getattr(model.config, "action_dim", 0):
            raise ValueError(
                "WorldModel needs an action-conditioned forecaster (action_dim > 0): train one with "
                "`action` in the data config (mmf-rl train experiment=world_model)"
            )
        action_stats = [f"{keys.FUTURE_ACTION}/mean", f"{keys.FUTURE_ACTION}/std"]
        require_stats("WorldModel", stats, action_stats, RUN_STATS_FIX)
        self.model = model.eval()
        self.normalizer = Normalizer({k: v.to(self.device) for k, v in stats.items()})
        self.constant_action_dims = self.normalizer.stats[f"{keys.FUTURE_ACTION}/std"] <= std_floor * (
            1 + 1e-4
        )
        self.stride = stride
        # How its history window counts a sensor lost for some steps (as the run trained it).
        self.per_step_presence = per_step_presence
        self.action_steps, self.action_dim = model.config.action_shape
        # How the forecast's scale is read (the run's model.output_distribution, saved with it).
        self.output_distribution = output_distribution_of(model)
        self.horizon, self.target_dim = model.config.horizon, model.config.target_dim

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        map_location: str | torch.device = "cpu",
        per_step_presence: bool | None = None,
    ) -> WorldModel:
        """The world model of a trained run.

        Args:
            path (str | os.PathLike): what `load_trained_model` reads.
            map_location (str | torch.device, optional): the model's device. Defaults to ``"cpu"``.
            per_step_presence (bool, optional): overrides the presence rule the run trained with
                (``data.partial_windows``, `trained_per_step_presence`).

        Returns:
            The world model, with its run's stride and ``std_floor``.

        Raises:
            ValueError: the run's model is not a world model; the message names ``path`` (an
                ensemble loads several).
        """
        model, stats, data_config = load_trained_model(path, map_location)
        per_step_presence = trained_per_step_presence(data_config, per_step_presence, f"WorldModel {path}")
        try:
            return cls(
                model,
                stats,
                stride=int(data_config.get("stride", 1)),
                std_floor=float(data_config.get("std_floor", 1e-3)),
                per_step_presence=per_step_presence,
            )
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error

    def history_window(self) -> HistoryWindow:
        """The env transform that writes the ``"history"`` window this model reads (its modalities,
        history, stride, normalisation and presence rule)."""
        return HistoryWindow.for_model(self.model, self.normalizer.stats, self.stride, self.per_step_presence)

    @property
    def modalities(self) -> list[keys.ModalitySpec]:
        """The sensors the model reads (its history window's)."""
        return self.model.modalities

    @property
    def token_shape(self) -> tuple[int, ...]:
        """The shape of one window's :meth:`encode` tokens: ``(N, d)``."""
        return len(self.model.token_modality), self.model.config.d_model

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    @torch.no_grad()
    def encode(self, window: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encode history windows, once per decision.

        Args:
            window (TensorDictBase): ``n`` history windows (a ``"history"`` entry of `HistoryWindow`).

        Returns:
            Tokens ``[n, N, d]``, token presence ``[n, N]`` and ``valid`` ``[n]`` (``N`` tokens: see
            :meth:`MultimodalForecaster.encode`).
        """
        specs = self.model.modalities
        # NaN/Inf under a present modality (a window built by hand) reads as absent, as in HistoryWindow.
        window = window.clone(False)
        for spec in specs:
            readable = ~keys.nonfinite_rows(window.get(spec.obs_key))
            window.set(spec.present_key, window.get(spec.present_key) & readable)
        present = torch.stack([window.get(s.present_key) for s in specs], dim=1).to(self.device)
        valid = present.any(1)
        token_modality = self.model.token_modality
        d_model = self.model.config.d_model
        no_tokens = torch.zeros(present.shape[0], len(token_modality), d_model, device=self.device)
        tokens, present = compute_on_rows(
            valid,
            lambda rows: self.model.encode((window if rows is None else window[rows.cpu()]).to(self.device)),
            (no_tokens, present[:, token_modality]),
        )
        return tokens, present, valid

    @torch.no_grad()
    def forecast(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """Forecast encoded histories under raw action sequences.

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens ``[n, N, d]``.
            present (torch.Tensor): its token presence ``[n, N]``.
            valid (torch.Tensor): its ``valid`` ``[n]``.
            actions (torch.Tensor): ``[n, N, S, A]`` raw actions (the env's units).

        Returns:
            ``[n, N, T, D]`` forecasts, in the target's units.
        """
        normalized, _ = self._decode(tokens, present, valid, actions)
        return self.normalizer.denormalize_target(normalized)

    @torch.no_grad()
    def forecast_distribution(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forecast` and its standard deviation, both ``[n, N, T, D]`` in target units, from the
        same decode. The standard deviation is the decoder's predictive one (its scale times the
        checkpoint's ``scale_calibration`` factors when it was calibrated, read as the model's output
        family says: the scale itself for the Gaussian, ``sqrt(2)`` times it for the Laplace,
        ``sqrt(df / (df - 2))`` times it for the Student-t) scaled by the target's training std:
        a forecast's spread has no offset, also for a target relative to now. Rows that cannot be
        encoded get the target's training std (the marginal, beside the marginal mean).

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens ``[n, N, d]``.
            present (torch.Tensor): its token presence ``[n, N]``.
            valid (torch.Tensor): its ``valid`` ``[n]``.
            actions (torch.Tensor): ``[n, N, S, A]`` raw actions.

        Returns:
            ``(forecast, std)``, each ``[n, N, T, D]``.
        """
        normalized, scale = self._decode(tokens, present, valid, actions)
        std = self.output_distribution.stddev(scale)
        return self.normalizer.denormalize_target(normalized), self.normalizer.denormalize_target_scale(std)

    def _decode(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised forecast location and scale ``[n, N, T, D]``: one decode of all candidates."""
        n, candidates = actions.shape[:2]
        prior_loc = torch.zeros(n, candidates, self.horizon, self.target_dim, device=self.device)

        def decode(rows: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
            index = slice(None) if rows is None else rows
            scaled = self.normalizer.normalize(keys.FUTURE_ACTION, actions.to(self.device)[index])
            scaled = scaled.masked_fill(self.constant_action_dims, 0.0)
            return self.model.decode_under_actions(tokens[index], present[index], scaled)

        # Rows that cannot be encoded: the marginal, a standard deviation of one (normalised).
        marginal_scale = torch.full_like(prior_loc, 1 / math.sqrt(self.output_distribution.variance))
        return compute_on_rows(valid, decode, (prior_loc, marginal_scale))
