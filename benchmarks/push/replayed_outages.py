"""Training outages drawn by the env's own outage processes: `ReplayedOutages`, the `OutageSampler` of
``benchmarks/bc_push.py --train-outages replayed``. Measured to change nothing (docs/results.md, "Training
on the outages the test plays, replayed"), so it lives with that experiment.

`DemonstrationLoader`'s ``dropout`` removes a sensor from a sample's whole window, independently
per sample, and a `LatchedForecastTable` draws the latch's age at random. In closed loop a sensor
fails along an episode instead (bursts of a few steps, a death, a whole episode), and what a policy
reads then follows the process: a camera that flickers leaves the policy's own window without it
while the latch, refreshed from a partial window, is fresh. A policy trained on the independent
draws meets such combinations for the first time in the test. `ReplayedOutages` replays every
recorded episode of a split through the transforms a policy reads in closed loop, stepped offline
on the recorded frames: each process's `ModalityDropout`, the policy's `HistoryWindow` and the
forecaster's transform; it keeps, per frame and replay, which sensors the policy's window holds and
the forecast (and age) served. A training batch draws one replay per sample (`draw`)::

    replayed = ReplayedOutages.replay(
        demonstrations, "train", [("all", None), ("camera bursts", ModalityDropout(["image"], ...))],
        policy.history_window(), LatchedForecastTransform.for_trained(..., denormalize=False),
    )
    train_bc(policy, demonstrations, config, dropout={}, forecasts=table, outages=replayed)

`train_bc` refuses a replay made through another window or forecast than the policy reads
(`ReplayedOutages.check_reads`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from tensordict import NestedKey
from torchrl.envs.transforms import Transform

from mmf_rl import keys
from mmf_rl.envs.modality_dropout import ModalityDropout
from mmf_rl.rl.bc import BCPolicy
from mmf_rl.rl.demonstrations import Demonstrations
from mmf_rl.rl.transforms import HistoryWindow

# What a forecast transform writes that a policy reads (the age only from a latched one).
FORECAST_KEYS = (keys.FORECAST_LOC, keys.FORECAST_SCALE, keys.FORECAST_AGE)
# Episodes replayed at once: the transforms keep a window per episode, images included.
EPISODES_PER_PASS = 256


@dataclass
class ReplayedOutages:
    """What the policy reads at each replayed frame, once per replay (see the module doc).

    Built by :meth:`replay`.

    Args:
        labels (list[str]): the outage process of each replay (``"all"``: none), ``R`` of them.
        replayed (torch.Tensor): ``bool [N]`` over the demonstrations' cache rows: the frames replayed.
        absent (dict[str, torch.Tensor]): ``{m: bool [R, N]}``: the policy's window lacks ``m`` (every
            modality it reads).
        forecast (dict[NestedKey, torch.Tensor]): ``{key: [R, N, ...]}``: what the forecast transform
            served (empty without one).
        history (int): the window's steps (`HistoryWindow`): a policy trained on the replay must read
            the same, or its window's absences are not those stored.
        stride (int): the window's stride, likewise.
        rule (str | None): the `LatchedForecastTransform` rule of the forecast served (``None``: fresh
            or none).
    """

    labels: list[str]
    replayed: torch.Tensor
    absent: dict[str, torch.Tensor]
    forecast: dict[NestedKey, torch.Tensor]
    history: int
    stride: int
    rule: str | None

    @classmethod
    @torch.no_grad()
    def replay(
        cls,
        demonstrations: Demonstrations,
        split: str,
        outages: Sequence[tuple[str, ModalityDropout | None]],
        window: HistoryWindow,
        forecast: Transform | None = None,
    ) -> ReplayedOutages:
        """Replay the episodes of ``split`` once per ``(label, ModalityDropout or None)`` of
        ``outages`` (a process replayed twice with another seed is two entries) through ``window``
        (the policy's) and ``forecast`` (`ForecastTransform` or `LatchedForecastTransform` with
        ``denormalize=False``, as the policy reads it in closed loop; ``None`` for a policy without)."""
        _check_replay_inputs(demonstrations, split, outages, forecast)
        starts, lengths = demonstrations.episodes(split)
        n = len(demonstrations.goal)
        replayed = torch.zeros(n, dtype=torch.bool)
        replayed[_episode_rows(starts, lengths)] = True
        stacks = [[t for t in (dropout, window, forecast) if t is not None] for _, dropout in outages]
        runs = [_replay_one(demonstrations, starts, lengths, stack) for stack in stacks]
        absent = {m: torch.stack([r[0][m] for r in runs]) for m in runs[0][0]}
        served = {k: torch.stack([r[1][k] for r in runs]) for k in runs[0][1]}
        rule = getattr(forecast, "rule", None)
        return cls(
            [label for label, _ in outages], replayed, absent, served, window.history, window.stride, rule
        )

    def draw(
        self, frames: torch.Tensor, generator: torch.Generator, with_forecasts: bool
    ) -> tuple[dict[str, torch.Tensor], dict[NestedKey, torch.Tensor]]:
        """One replay per sample of ``frames``, uniform over the replays: the modalities each
        sample's window lacks (`DemonstrationLoader`'s ``absent``) and, ``with_forecasts``, the
        forecast entries served there."""
        if not bool(self.replayed[frames].all()):
            missing = frames[~self.replayed[frames]][:5].tolist()
            raise ValueError(
                f"ReplayedOutages: frames {missing} were not replayed; replay the split they belong to"
            )
        if with_forecasts and not self.forecast:
            raise ValueError(
                "ReplayedOutages: the replay served no forecast and the policy reads one; replay with the "
                "policy's forecast transform (ReplayedOutages.replay(..., forecast=...))"
            )
        which = torch.randint(len(self.labels), (len(frames),), generator=generator)
        absent = {m: a[which, frames] for m, a in self.absent.items()}
        served = {k: v[which, frames] for k, v in self.forecast.items()} if with_forecasts else {}
        return absent, served

    def check_reads(self, policy: BCPolicy) -> None:
        """Raise unless these outages were replayed through what ``policy`` reads in closed loop: its
        window, and its forecast (with the age and rule of a latched one) or none."""
        config = policy.config
        if (self.history, self.stride) != (config.history, config.stride):
            raise ValueError(
                f"train_bc: the outages were replayed through a window of {self.history} steps, stride "
                f"{self.stride}, the policy reads {config.history}, stride {config.stride}; replay them "
                "through policy.history_window()"
            )
        if config.forecast_shape is None:
            return
        served, rule = self.forecast.get(keys.FORECAST_LOC), self.rule
        if (
            served is None
            or tuple(served.shape[-2:]) != config.forecast_shape
            or rule != config.latched_forecast
        ):
            found = (
                "no forecast" if served is None else f"forecasts {list(served.shape[-2:])}, latch rule {rule}"
            )
            raise ValueError(
                f"train_bc: the policy reads forecasts {list(config.forecast_shape)} (T, D), latch rule "
                f"{config.latched_forecast} (None: fresh), the replayed outages served {found}; replay them "
                "with the forecast transform the policy reads in closed loop (LatchedForecastTransform of "
                "its rule for a latched policy, ForecastTransform else; denormalize=False)"
            )

    def checkpoint_meta(self) -> dict:
        """The replays' labels, which a run checks before it reuses the policy."""
        return {"replayed_outages": list(self.labels)}

    @property
    def droppable(self) -> tuple[str, ...]:
        """The modalities some replay removes from some window."""
        return tuple(m for m, a in self.absent.items() if bool(a.any()))

    def absent_fraction(self) -> dict[str, dict[str, float]]:
        """``{label: {m: fraction of the replayed frames whose window lacks m}}``, for the results; over
        every replay of a label (a process replayed with several seeds has one label)."""
        fractions = {}
        for label in dict.fromkeys(self.labels):
            replays = torch.tensor([own == label for own in self.labels])
            fractions[label] = {
                m: float(a[replays][:, self.replayed].float().mean()) for m, a in self.absent.items()
            }
        return fractions


def _check_replay_inputs(
    demonstrations: Demonstrations, split: str, outages: Sequence, forecast: Transform | None
) -> None:
    """Raise unless there is something to replay, and the forecast is in the frame a policy reads."""
    if not outages:
        raise ValueError("ReplayedOutages.replay: no outage process; give ('all', None) at least")
    if getattr(forecast, "denormalize", False):
        raise ValueError(
            "ReplayedOutages.replay: the forecast transform writes forecasts in the target's units, a "
            "policy reads them in the forecaster's normalised frame; build it with denormalize=False"
        )
    if not len(demonstrations.split_frames.get(split, ())):
        sizes = {name: len(frames) for name, frames in demonstrations.split_frames.items()}
        raise ValueError(
            f"ReplayedOutages.replay: the {split!r} split has no demonstration frame (frames per split: "
            f"{sizes}); replay the split the policy trains on"
        )


def _episode_rows(starts: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    return torch.cat([torch.arange(s, s + n) for s, n in zip(starts.tolist(), lengths.tolist(), strict=True)])


def _replay_one(
    demonstrations: Demonstrations, starts: torch.Tensor, lengths: torch.Tensor, transforms: list[Transform]
) -> tuple[dict[str, torch.Tensor], dict[NestedKey, torch.Tensor]]:
    """One replay of every episode through ``transforms`` (in env order), a pass of episodes at a
    time; returns the window's absences and the forecast entries per cache row."""
    n = len(demonstrations.goal)
    absent: dict[str, torch.Tensor] = {}
    served: dict[NestedKey, torch.Tensor] = {}
    for first in range(0, len(starts), EPISODES_PER_PASS):
        chunk = slice(first, first + EPISODES_PER_PASS)
        for t, rows, out in _stepped(demonstrations, starts[chunk], lengths[chunk], transforms):
            inside = t < lengths[chunk]
            lacks = {s.name: ~out.get((keys.HISTORY, *s.present_key)) for s in demonstrations.specs}
            _write(absent, lacks, rows, inside, n)
            _write(served, {k: out.get(k) for k in FORECAST_KEYS if k in out.keys(True)}, rows, inside, n)
    return absent, served


def _stepped(demonstrations: Demonstrations, starts: torch.Tensor, lengths: torch.Tensor, transforms):
    """``(t, rows, output)`` of each step of the episodes starting at ``starts``, played together
    (an episode past its end repeats its last frame; its outputs there are not kept)."""
    for t in range(int(lengths.max())):
        rows = starts + torch.minimum(torch.tensor(t), lengths - 1)
        out = demonstrations.env_observation(rows)
        for transform in transforms:
            out = transform.observe_reset(out) if t == 0 else transform.observe_step(out)
        yield t, rows, out


def _write(
    store: dict, values: Mapping[NestedKey, torch.Tensor], rows: torch.Tensor, inside: torch.Tensor, n: int
) -> None:
    """Store ``values`` of the ``inside`` rows at their cache ``rows``; a key's store is made at its
    first write (which forecast keys a transform writes is known only then)."""
    for key, value in values.items():
        if key not in store:
            store[key] = value.new_zeros((n, *value.shape[1:]))
        store[key][rows[inside]] = value[inside]
