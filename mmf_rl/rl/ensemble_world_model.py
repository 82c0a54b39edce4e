"""Several world models planned with as one: their mean forecast, their disagreement as its spread."""

from __future__ import annotations

import os
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase

from mmf_rl import keys
from mmf_rl.rl.transforms import HistoryWindow
from mmf_rl.rl.world_model import WorldModel

# How far two members' normalisation statistics may differ (relative and absolute) and still be
# read through one history window.
STATS_TOLERANCE = 1e-6


class EnsembleWorldModel:
    """Independently trained `WorldModel` s (e.g. training seeds on one data config) as one world
    model, PETS-style: wherever a `WorldModel` plans (`SequenceCEMPlanner`, `MPCActor`,
    `forecast_and_score`, `ForecasterWorldModelEnv`), an ensemble plans too.

    Its forecast is the members' mean forecast. Its spread (:meth:`forecast_distribution`) is the
    members' **disagreement**: per step and dim, the standard deviation over members of their mean
    forecasts (``correction=0``, target units) — not the decoder's own standard deviation. The
    decoder's std is *aleatoric*: it is the noise of the outcome the data showed, largest for
    plans that push the block (a push's outcome varies), so a penalty on it keeps a planner off
    the block. The disagreement is *epistemic*: models fitted to the same data agree where the
    data pinned the outcome down and diverge where it did not (states and actions the recording
    rarely visited), which is what a planner should avoid relying on. An ensemble of one member
    forecasts as the member, with zero spread.

    :meth:`encode` encodes the window once per member and stacks the encodings on a member dim
    after the batch dim: tokens ``[n, K, N, d]``, token presence ``[n, K, N]`` and ``valid``
    ``[n]``, so the call ``forecast(*encoded, actions)`` is the same as a `WorldModel`'s. Cost:
    one encode per member per decision, one decode per member per batch of candidates.

    Members must read the same history window (modalities, history, stride, presence rule,
    normalisation statistics within `STATS_TOLERANCE`), take the same actions (steps, dims) and
    forecast the same target (horizon, dims), so one `HistoryWindow` serves all and the planner
    samples in one action frame; and their encodings must stack (token count and width: the same
    model config). Otherwise the constructor raises, naming the member and the difference.

    Args:
        members (Sequence[WorldModel]): the world models, on one device.
        names (Sequence[str], optional): what errors call each member (default ``member i``;
            `from_checkpoints`: its path).

    Raises:
        ValueError: no member, as many names as members, or a member that does not match the first
            (named, with the difference).

    Examples:
        >>> import torch
        >>> from mmf_rl.keys import ModalitySpec
        >>> from mmf_rl.models import ForecasterConfig, MultimodalForecaster
        >>> force = ModalitySpec("force", "sequence", (6,))
        >>> proprio = ModalitySpec("proprio", "sequence", (17,))
        >>> sizes = dict(history=4, horizon=5, d_model=16, d_latent=4, num_heads=2)
        >>> sizes.update(action_dim=4, action_steps=5)  # the push env's actions over the 5 steps
        >>> model = MultimodalForecaster(ForecasterConfig([force, proprio], **sizes))
        >>> stats = {  # its training run's normalisation statistics (a checkpoint's tensors)
        ...     "force/mean": torch.zeros(6), "force/std": torch.ones(6),
        ...     "proprio/mean": torch.zeros(17), "proprio/std": torch.ones(17),
        ...     "target/mean": torch.zeros(2), "target/std": torch.ones(2),
        ...     "future_action/mean": torch.zeros(4), "future_action/std": torch.ones(4),
        ... }
        >>> from tensordict import TensorDict
        >>> from mmf_rl.rl import EnsembleWorldModel, WorldModel
        >>> members = [WorldModel(MultimodalForecaster(model.config), stats) for _ in range(3)]  # 3 inits
        >>> ensemble = EnsembleWorldModel(members)
        >>> window = TensorDict({
        ...     ("obs", "force"): torch.randn(2, 4, 6),
        ...     ("present", "force"): torch.ones(2, dtype=torch.bool),
        ...     ("obs", "proprio"): torch.randn(2, 4, 17),
        ...     ("present", "proprio"): torch.ones(2, dtype=torch.bool),
        ... }, batch_size=[2])
        >>> tokens, present, valid = ensemble.encode(window)
        >>> tokens.shape  # [n, K members, N tokens, d]
        torch.Size([2, 3, 2, 16])
        >>> actions = torch.zeros(2, 8, 5, 4)  # 8 candidate sequences per window
        >>> mean, disagreement = ensemble.forecast_distribution(tokens, present, valid, actions)
        >>> mean.shape, bool((disagreement > 0).all())
        (torch.Size([2, 8, 5, 2]), True)
    """

    def __init__(self, members: Sequence[WorldModel], names: Sequence[str] | None = None):
        members = list(members)
        if not members:
            raise ValueError("EnsembleWorldModel needs at least one member world model")
        names = [f"member {i}" for i in range(len(members))] if names is None else list(names)
        if len(names) != len(members):
            raise ValueError(f"EnsembleWorldModel: {len(names)} names for {len(members)} members")
        for member, name in zip(members[1:], names[1:], strict=True):
            difference = _difference(members[0], member)
            if difference:
                raise ValueError(
                    f"EnsembleWorldModel: {name} does not match {names[0]}: {difference}; ensemble only "
                    "world models trained on the same data config (e.g. different trainer.seed)"
                )
        self.members, self.names = members, names
        first = members[0]
        # The members' statistics match: the first's action frame is every member's (the planner
        # samples in it).
        self.normalizer, self.constant_action_dims = first.normalizer, first.constant_action_dims
        self.stride = first.stride
        self.action_steps, self.action_dim = first.action_steps, first.action_dim
        self.horizon, self.target_dim = first.horizon, first.target_dim

    @classmethod
    def from_checkpoints(
        cls, paths: Sequence[str | os.PathLike], map_location: str | torch.device = "cpu"
    ) -> EnsembleWorldModel:
        """The ensemble of the world models at ``paths``.

        Args:
            paths (Sequence[str | os.PathLike]): each what `WorldModel.from_checkpoint` reads.
            map_location (str | torch.device, optional): their device. Defaults to ``"cpu"``.

        Returns:
            The ensemble; errors name each member by its path.
        """
        return cls([WorldModel.from_checkpoint(p, map_location) for p in paths], [str(p) for p in paths])

    def history_window(self) -> HistoryWindow:
        """The env transform that writes the ``"history"`` window every member reads."""
        return self.members[0].history_window()

    @property
    def modalities(self) -> list[keys.ModalitySpec]:
        return self.members[0].modalities

    @property
    def token_shape(self) -> tuple[int, ...]:
        """The shape of one window's :meth:`encode` tokens: ``(K, N, d)``."""
        return len(self.members), *self.members[0].token_shape

    @property
    def device(self) -> torch.device:
        return self.members[0].device

    @torch.no_grad()
    def encode(self, window: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encode history windows with every member.

        Args:
            window (TensorDictBase): ``n`` history windows.

        Returns:
            Every member's tokens ``[n, K, N, d]`` and token presence ``[n, K, N]``, and ``valid``
            ``[n]`` (the rows with a present modality: the same for every member, as they read one
            window).
        """
        encoded = [member.encode(window) for member in self.members]
        tokens = torch.stack([e[0] for e in encoded], dim=1)
        present = torch.stack([e[1] for e in encoded], dim=1)
        return tokens, present, encoded[0][2]

    @torch.no_grad()
    def forecast(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """The members' mean forecast for raw action sequences.

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens ``[n, K, N, d]``.
            present (torch.Tensor): its token presence ``[n, K, N]``.
            valid (torch.Tensor): its ``valid`` ``[n]``.
            actions (torch.Tensor): ``[n, N, S, A]`` raw actions.

        Returns:
            ``[n, N, T, D]``, target units.
        """
        return self._member_forecasts(tokens, present, valid, actions).mean(0)

    @torch.no_grad()
    def forecast_distribution(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`forecast` and the members' disagreement, both ``[n, N, T, D]`` in target units. Rows
        without a present modality get every member's marginal mean, equal across members (their
        statistics match): no disagreement there.

        Args:
            tokens (torch.Tensor): :meth:`encode`'s tokens ``[n, K, N, d]``.
            present (torch.Tensor): its token presence ``[n, K, N]``.
            valid (torch.Tensor): its ``valid`` ``[n]``.
            actions (torch.Tensor): ``[n, N, S, A]`` raw actions.

        Returns:
            ``(mean, disagreement)``, each ``[n, N, T, D]``.
        """
        forecasts = self._member_forecasts(tokens, present, valid, actions)
        return forecasts.mean(0), forecasts.std(0, correction=0)

    def _member_forecasts(
        self, tokens: torch.Tensor, present: torch.Tensor, valid: torch.Tensor, actions: torch.Tensor
    ) -> torch.Tensor:
        """Each member's forecast ``[K, n, N, T, D]`` from its own encoding."""
        if tokens.dim() != 4 or tokens.shape[1] != len(self.members):
            raise ValueError(
                f"EnsembleWorldModel: tokens of shape {list(tokens.shape)} are not an encoding of its "
                f"{len(self.members)} members ([n, {len(self.members)}, N, d]); pass what its encode returns"
            )
        return torch.stack(
            [
                member.forecast(tokens[:, k], present[:, k], valid, actions)
                for k, member in enumerate(self.members)
            ]
        )


def _difference(reference: WorldModel, member: WorldModel) -> str:
    """What makes ``member`` unfit to share ``reference``'s window, actions and target ('' if nothing)."""

    def read(model: WorldModel) -> dict[str, object]:
        return {
            "modalities": [(s.name, s.kind, s.shape) for s in model.modalities],
            "history": model.model.config.history,
            "stride": model.stride,
            "per-step presence (data.partial_windows)": model.per_step_presence,
            "action steps x dims": (model.action_steps, model.action_dim),
            "horizon": model.horizon,
            "target dims": model.target_dim,
            "tokens x width": model.token_shape,
            "normalisation statistics": sorted(model.normalizer.stats),
        }

    expected, found = read(reference), read(member)
    for name, value in expected.items():
        if found[name] != value:
            return f"{name} {found[name]} (expected {value})"
    for key, value in reference.normalizer.stats.items():
        other = member.normalizer.stats[key]
        if other.shape != value.shape or not torch.allclose(
            other.to(value.device), value, rtol=STATS_TOLERANCE, atol=STATS_TOLERANCE
        ):
            return f"normalisation statistic {key!r} differs by more than {STATS_TOLERANCE}"
    return ""
