"""The data config: which dataset, which features are which modalities, window geometry.

Built from a plain dict (Hydra YAML feeds it) with :meth:`DataConfig.from_dict`; ``to_dict``
gives it back so a run can store exactly what it trained on, missingness protocol included.
"""

from __future__ import annotations

import os
from dataclasses import MISSING, asdict, dataclass, field, fields
from pathlib import Path

from mmf_rl.configuration import reject_unknown_keys
from mmf_rl.keys import MODALITY_KINDS

SPLIT_NAMES = ("train", "val", "test")


@dataclass
class ModalityConfig:
    """One modality read from one dataset feature.

    Args:
        feature (str): the dataset feature it reads (a camera ``observation.images.<cam>`` or a vector).
        kind (str, optional): ``"image"``, ``"sequence"`` (a vector window) or ``"vector"`` (the window's last
            step only). Unset: from the feature's dtype, video/image → ``"image"``, vector → ``"sequence"``.
        dims (list[int], optional): the feature dims to keep (all when unset), for a vector that mixes several
            sensors.
        valid_feature (str, optional): a per-frame boolean feature saying when this modality is valid. Unset:
            ``"<feature>_valid"`` (for a camera ``observation.images.<cam>``,
            ``observation.<cam>_camera_valid``, as the recorder writes it) if the dataset has it.
        required (bool, optional): an absent modality (missing video, NaN span) is an error, not a warning.
        encoder (str, optional): the unimodal encoder (``mmf_rl.models.encoders``); unset: the kind's default.
        encoder_kwargs (dict, optional): keyword arguments of that encoder, where the feature's layout decides
            them (e.g. ``slot_dim`` of an agent-slot encoder).
        raw_dims (list[int], optional): indices (after ``dims``) left unnormalised, so flags such as a
            per-slot ``valid`` keep their exact 0/1 meaning, which a mean/std shift would make data-dependent.
        allow_absent (bool, optional): accept losing the modality on more than half of the frames; without it
            that is an error, since the model would silently train without it (e.g. a declared camera whose
            video files were never recorded).
        planar (list[list[int]], optional): ``[x, y]`` pairs of dims (after ``dims``) that are vectors in the
            ground plane (positions, velocities, offsets): ``augment.rotation`` turns them
            (:mod:`~mmf_rl.datasets.planar`).
        top_down (bool, optional): a camera that is a map of the ground plane (world ``x`` right, ``y`` up),
            turned with the planar dims by ``augment.rotation``.

    Raises:
        ValueError: an unknown ``kind``, or ``dims``, ``raw_dims`` or ``planar`` that are not whole-number
            indices (pairs).
    """

    feature: str
    kind: str | None = None
    dims: list[int] | None = None
    valid_feature: str | None = None
    required: bool = False
    encoder: str | None = None
    encoder_kwargs: dict | None = None
    raw_dims: list[int] | None = None
    allow_absent: bool = False
    planar: list[list[int]] | None = None
    top_down: bool = False

    def __post_init__(self):
        if self.kind is not None and self.kind not in MODALITY_KINDS:
            raise ValueError(
                f"modality feature {self.feature!r}: unknown kind {self.kind!r}; expected one of "
                f"{sorted(MODALITY_KINDS)} or leave it unset to infer it from the feature dtype"
            )
        self.dims = _indices(self.dims, f"modality feature {self.feature!r}: dims")
        self.raw_dims = _indices(self.raw_dims, f"modality feature {self.feature!r}: raw_dims")
        self.planar = _pairs(self.planar, f"modality feature {self.feature!r}: planar")


@dataclass
class TargetReference:
    """The frame a target is forecast in: another vector feature's value at the window's last
    observed frame (``target.relative_to``).

    Args:
        feature (str): a vector feature of the dataset (for the push data the gripper position,
            ``observation.state`` dims ``[0, 1]``).
        dims (list[int], optional): which of its dims, one per target dim, in the target's order (all when
            unset).
    """

    feature: str
    dims: list[int] | None = None

    def __post_init__(self):
        self.dims = _indices(self.dims, "target.relative_to.dims")


@dataclass
class TargetConfig:
    """The forecast variable.

    Args:
        feature (str): a vector feature of the dataset.
        dims (list[int], optional): which of its dims to forecast (all when unset).
        relative (bool, optional): forecast the change from the window's last observed frame (subtracted from
            the future and from ``target_past``; the normalisation statistics then describe those
            displacements) instead of absolute values. The model then predicts motion, not where things are,
            which is what it needs when the target's current value is not one of its inputs (the push task's
            object position).
        relative_to (TargetReference, optional): forecast the target minus another feature's dims at the
            window's last observed frame (:class:`TargetReference`, e.g. the object's position relative to the
            gripper: where the object is, in a frame a policy acts in). Subtracted from the future and from
            ``target_past``; the normalisation statistics describe the offsets. Excludes ``relative``.
        planar (list[list[int]], optional): ``[x, y]`` pairs of the target's dims (after ``dims``) that are
            vectors in the ground plane, turned by ``augment.rotation`` with the inputs' planar dims.

    Raises:
        ValueError: both ``relative`` and ``relative_to`` set, or malformed ``dims`` or ``planar``.
    """

    feature: str
    dims: list[int] | None = None
    relative: bool = False
    relative_to: TargetReference | None = None
    planar: list[list[int]] | None = None

    def __post_init__(self):
        self.dims = _indices(self.dims, "target.dims")
        self.planar = _pairs(self.planar, "target.planar")
        if self.relative_to is not None and not isinstance(self.relative_to, TargetReference):
            self.relative_to = _entry(TargetReference, self.relative_to, "target.relative_to")
        if self.relative and self.relative_to is not None:
            raise ValueError(
                "data config: `target.relative` and `target.relative_to` both set; a target is measured "
                "either from its own last observed value (relative: true) or from another feature's "
                "(relative_to): keep one"
            )

    @property
    def anchored(self) -> bool:
        """The forecast is an offset from a value at the window's last observed frame."""
        return self.relative or self.relative_to is not None


@dataclass
class ActionConfig:
    """The action feature a world model is conditioned on (``"future_action"`` in a batch).

    A window at ``t`` carries the actions of frames ``t .. t + T·stride - 1``: in LeRobot a frame's
    ``action`` is the command sent after that frame's observation, so these are exactly the
    commands that move the system from the last observed frame to the last forecast one.

    Args:
        feature (str, optional): the action feature (LeRobot's ``"action"`` by default).
        dims (list[int], optional): which of its dims condition the model (all when unset).
        planar (list[list[int]], optional): ``[x, y]`` pairs of those dims that are vectors in the ground
            plane (a commanded displacement), turned by ``augment.rotation`` with the observations.
    """

    feature: str = "action"
    dims: list[int] | None = None
    planar: list[list[int]] | None = None

    def __post_init__(self):
        self.dims = _indices(self.dims, "action.dims")
        self.planar = _pairs(self.planar, "action.planar")


@dataclass
class OutageConfig:
    """Replayed sensor outages for one modality (``missing: {m: {fraction: f, mean_burst: L}}``),
    so a model trains for the outages its sensor shows (``mmf-rl inspect`` measures both).

    Args:
        fraction (float): about this share of the training frames are out (in ``[0, 1)``).
        mean_burst (float): the mean length of a simulated outage, in frames (``>= 1``).
    """

    fraction: float
    mean_burst: float

    def __post_init__(self):
        self.fraction, self.mean_burst = float(self.fraction), float(self.mean_burst)
        if not 0.0 <= self.fraction < 1.0 or self.mean_burst < 1.0:
            raise ValueError(
                f"data config: an outage needs 0 <= fraction < 1 and mean_burst >= 1 (frames), found "
                f"fraction={self.fraction}, mean_burst={self.mean_burst}"
            )


OBSERVED = "observed"
# How video frames are matched to parquet rows: by the row's `timestamp` (lerobot's way), or by its
# position in the episode (frame k at k / fps), for recordings whose timestamps drift off k / fps.
VIDEO_SYNC_MODES = ("timestamp", "frame_index")


@dataclass
class DataConfig:
    """Everything the pipeline needs to turn a LeRobot dataset into forecasting windows.

    A sample at window index ``t`` observes frames ``t-(H-1)s .. t`` and forecasts
    ``t+s .. t+Ts`` (``s = stride``), all inside one episode. :meth:`from_dict` builds it from plain
    data (what the Hydra ``data`` config holds), where a modality may be given as just its feature name.

    Args:
        modalities (dict[str, ModalityConfig]): the model's inputs, name → :class:`ModalityConfig`.
        target (TargetConfig): the forecast variable.
        root (str, optional): the dataset's directory; ``None`` fetches ``repo_id`` from the Hugging Face
            hub.
        repo_id (str, optional): the dataset's hub name (its window cache is named after it when ``root``
            is unset). Defaults to ``"local/dataset"``.
        history (int, optional): ``H``, observed steps per window. Defaults to ``10``.
        horizon (int, optional): ``T``, forecast steps per window. Defaults to ``10``.
        stride (int, optional): ``s``, frames between two steps of a window (subsamples a high frame
            rate). Defaults to ``1``.
        image_size (tuple[int, int], optional): ``(height, width)`` the camera frames are resized to in
            the cache. Defaults to ``(64, 64)``.
        include_target_past (bool, optional): add ``"target_past"``, the target's own history, to every
            window: the input of the constant-velocity reference that ``eval`` reports. Defaults to
            ``False``.
        split_fractions (tuple[float, float, float], optional): train/val/test shares of the selected
            episodes, cut at random. Defaults to ``(0.8, 0.1, 0.1)``.
        split_seed (int, optional): the seed of that cut. Defaults to ``0``.
        std_floor (float, optional): the smallest normalisation std, so a constant feature does not blow
            up. Defaults to ``1e-3``.
        missing (dict[str, float | OutageConfig] | str, optional): the training missingness protocol.
            ``{modality: p}`` removes ``m`` from a fixed fraction ``p`` of the training windows;
            ``{modality: {fraction, mean_burst}}`` replays outages (:class:`OutageConfig`) on top of the
            data's own; ``"observed"`` replays, for every modality, the outages measured in the training
            split (``WindowDataset.observed_outages``). Defaults to none.
        missing_seed (int, optional): the seed of those removals and replays. Defaults to ``0``.
        tolerance_s (float, optional): how far a decoded video frame may be from a row's ``timestamp``
            (lerobot's ``tolerance_s``). Defaults to ``1e-4``.
        cache_dir (str, optional): where window caches live; unset: ``windows/`` under
            ``$MMF_RL_CACHE``, else under ``~/.cache/mmf_rl``.
        action (ActionConfig, optional): the actions applied over the horizon, added to every window for
            an action-conditioned world model (none when unset).
        episodes (list[int], optional): the episode indices to use, as lerobot selects them (all when
            unset); only the selected episodes are decoded into the window cache.
        exclude_episodes (list[int], optional): episodes removed from that selection (e.g. damaged ones).
        split (dict[str, list[int]], optional): ``{train: [...], val: [...], test: [...]}`` names the
            split instead of ``split_fractions`` (a split left out is empty; without ``episodes``, the
            union of the lists is the selection). The split is always by episode, so no window leaks
            across.
        video_sync (str, optional): how video frames are matched to parquet rows: ``"timestamp"``
            (default) decodes each row's ``timestamp`` within ``tolerance_s`` (as lerobot does);
            ``"frame_index"`` decodes frame ``k`` of an episode at ``k / fps`` of its video segment, for
            recordings whose timestamps are wall-clock stamps drifting from ``k / fps`` (``mmf-rl
            inspect`` measures it).
        partial_windows (bool, optional): a windowed modality present at some steps of a window (not
            all) is present for it, with ``("present_steps", m)`` marking its steps, instead of absent
            for the whole window. Applies to the windows the cache keeps (those with a modality present
            throughout). Defaults to ``False``.

    Raises:
        ValueError: an invalid setting (no modality, a reserved modality name, a size below 1, fractions
            that do not sum to 1, a bad ``missing`` entry, an episode listed twice or in two splits, an
            unknown ``video_sync``); the message names the key.

    Examples:
        >>> from mmf_rl.datasets import DataConfig
        >>> config = DataConfig.from_dict({
        ...     "root": "data/my_robot",
        ...     "modalities": {"wrist": "observation.images.wrist", "joints": "observation.state"},
        ...     "target": {"feature": "observation.state", "dims": [0, 1]},
        ...     "history": 8,
        ...     "horizon": 4,
        ... })
        >>> config.modalities["joints"]
        ModalityConfig(feature='observation.state', kind=None, dims=None, ...)
        >>> config.horizon, config.split_fractions
        (4, (0.8, 0.1, 0.1))
    """

    modalities: dict[str, ModalityConfig]
    target: TargetConfig
    root: str | None = None
    repo_id: str = "local/dataset"
    history: int = 10
    horizon: int = 10
    stride: int = 1
    image_size: tuple[int, int] = (64, 64)
    include_target_past: bool = False
    split_fractions: tuple[float, float, float] = (0.8, 0.1, 0.1)
    split_seed: int = 0
    std_floor: float = 1e-3
    missing: dict[str, float | OutageConfig] | str = field(default_factory=dict)
    missing_seed: int = 0
    tolerance_s: float = 1e-4
    cache_dir: str | None = None
    action: ActionConfig | None = None
    episodes: list[int] | None = None
    exclude_episodes: list[int] = field(default_factory=list)
    split: dict[str, list[int]] | None = None
    video_sync: str = "timestamp"
    partial_windows: bool = False

    def __post_init__(self):
        self._check_episode_lists()
        if self.video_sync not in VIDEO_SYNC_MODES:
            raise ValueError(
                f"data config: `video_sync` must be one of {list(VIDEO_SYNC_MODES)}, found "
                f"{self.video_sync!r}"
            )
        if not self.modalities:
            raise ValueError("data config: `modalities` is empty; map at least one name to a dataset feature")
        reserved = {"target", "future_action"} & set(self.modalities)
        if reserved:
            raise ValueError(
                f"data config: modality name(s) {sorted(reserved)} are reserved (normalisation "
                "statistics use them); rename the modality"
            )
        for name, value in [("history", self.history), ("horizon", self.horizon), ("stride", self.stride)]:
            if int(value) < 1:
                raise ValueError(f"data config: `{name}` must be >= 1, found {value}")
        self.image_size = tuple(int(s) for s in self.image_size)
        if len(self.image_size) != 2 or min(self.image_size) < 1:
            raise ValueError(
                f"data config: `image_size` must be [height, width], found {list(self.image_size)}"
            )
        self.split_fractions = tuple(float(f) for f in self.split_fractions)
        if (
            len(self.split_fractions) != len(SPLIT_NAMES)
            or min(self.split_fractions) < 0
            or abs(sum(self.split_fractions) - 1.0) > 1e-6
        ):
            raise ValueError(
                f"data config: `split_fractions` must be 3 non-negative numbers (train, val, test) "
                f"summing to 1, found {list(self.split_fractions)}"
            )
        if isinstance(self.missing, str) and self.missing != OBSERVED:
            raise ValueError(
                f"data config: `missing` must be a mapping {{modality: fraction}} or {OBSERVED!r}, found "
                f"{self.missing!r}"
            )
        for name, p in ({} if isinstance(self.missing, str) else self.missing).items():
            if name not in self.modalities:
                raise ValueError(
                    f"data config: `missing` names modality {name!r}, which is not one of "
                    f"{sorted(self.modalities)}"
                )
            if not isinstance(p, OutageConfig) and not 0.0 <= float(p) <= 1.0:
                raise ValueError(f"data config: `missing.{name}` must be a fraction in [0, 1], found {p}")
        if self.std_floor <= 0:
            raise ValueError(f"data config: `std_floor` must be > 0, found {self.std_floor}")

    def _check_episode_lists(self) -> None:
        def ids(value, key: str) -> list[int]:
            if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
                raise ValueError(f"data config: `{key}` must be a list of episode indices, found {value!r}")
            out = []
            for e in value:
                if isinstance(e, bool) or not isinstance(e, int) or e < 0:
                    raise ValueError(
                        f"data config: `{key}` must hold episode indices (integers >= 0), found {e!r}"
                    )
                out.append(int(e))
            repeated = sorted({e for e in out if out.count(e) > 1})
            if repeated:
                raise ValueError(f"data config: `{key}` lists episode(s) {repeated} more than once")
            return out

        if self.episodes is not None:
            self.episodes = ids(self.episodes, "episodes")
        self.exclude_episodes = ids(self.exclude_episodes or [], "exclude_episodes")
        if self.split is None:
            return
        if not isinstance(self.split, dict):
            raise ValueError(
                f"data config: `split` must map {list(SPLIT_NAMES)} to episode lists, found {self.split!r}"
            )
        unknown = sorted(set(self.split) - set(SPLIT_NAMES))
        if unknown:
            raise ValueError(
                f"data config: `split` has unknown split(s) {unknown}; expected some of {list(SPLIT_NAMES)}"
            )
        self.split = {str(name): ids(value or [], f"split.{name}") for name, value in self.split.items()}
        if not self.split.get("train"):
            raise ValueError("data config: `split.train` is empty; an explicit split needs training episodes")
        names = list(self.split)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                both = sorted(set(self.split[a]) & set(self.split[b]))
                if both:
                    raise ValueError(
                        f"data config: episode(s) {both} are in both `split.{a}` and `split.{b}`; "
                        "an episode belongs to one split"
                    )

    @classmethod
    def from_dict(cls, d: dict) -> DataConfig:
        """Build from plain data. A modality may be given as just its feature name.

        Args:
            d (dict): the config's keys (``modalities`` and ``target`` required).

        Returns:
            The config, checked.

        Raises:
            ValueError: an unknown or missing key, or an invalid setting.
        """
        d = dict(d)
        reject_unknown_keys(cls, d, "data config")
        for required in ("modalities", "target"):
            if required not in d:
                raise ValueError(f"data config: missing key `{required}`")
        d["modalities"] = {
            str(name): _entry(ModalityConfig, value, f"modalities.{name}")
            for name, value in dict(d["modalities"]).items()
        }
        d["target"] = _entry(TargetConfig, d["target"], "target")
        missing = d.get("missing", {})
        if not isinstance(missing, str):
            missing = {str(k): _missing_entry(k, v) for k, v in dict(missing).items()}
        d["missing"] = missing
        if d.get("action") is not None:
            d["action"] = _entry(ActionConfig, d["action"], "action")
        return cls(**d)

    @property
    def has_planar_values(self) -> bool:
        """Some modality, the target or the action is declared in the ground plane (``planar``,
        ``top_down``): what ``augment.rotation`` turns."""
        declared = [m.planar or m.top_down for m in self.modalities.values()] + [self.target.planar]
        return any(declared) or bool(self.action is not None and self.action.planar)

    @property
    def window_dropout(self) -> dict[str, float]:
        """The ``{modality: fraction of training windows}`` part of ``missing``."""
        return (
            {}
            if isinstance(self.missing, str)
            else {k: v for k, v in self.missing.items() if not isinstance(v, OutageConfig)}
        )

    @property
    def replayed_outages(self) -> dict[str, OutageConfig] | str:
        """The outage-replay part of ``missing``: ``{modality: OutageConfig}``, or ``"observed"``."""
        return (
            self.missing
            if isinstance(self.missing, str)
            else {k: v for k, v in self.missing.items() if isinstance(v, OutageConfig)}
        )

    def to_dict(self) -> dict:
        """The config as plain data, what :meth:`from_dict` reads back (a run saves it)."""
        d = asdict(self)
        d["image_size"] = list(self.image_size)
        d["split_fractions"] = list(self.split_fractions)
        return d

    def cache_fields(self) -> dict:
        """The fields that decide what the window cache contains (its key, with the files)."""
        fields = {
            "modalities": {
                name: {"feature": m.feature, "kind": m.kind, "dims": m.dims, "valid_feature": m.valid_feature}
                for name, m in sorted(self.modalities.items())
            },
            "target": {
                "feature": self.target.feature,
                "dims": self.target.dims,
            },  # `relative` is applied at batch time
            "history": self.history,
            "horizon": self.horizon,
            "stride": self.stride,
            "image_size": list(self.image_size),
            "tolerance_s": self.tolerance_s,
        }
        reference = self.target.relative_to
        if reference is not None:  # only when set: caches built before it existed stay valid
            fields["target"]["relative_to"] = {"feature": reference.feature, "dims": reference.dims}
        if self.action is not None:  # only when set: caches built before actions existed stay valid
            fields["action"] = {"feature": self.action.feature, "dims": self.action.dims}
        if self.video_sync != "timestamp":  # likewise: caches synced by timestamp keep their key
            fields["video_sync"] = self.video_sync
        return fields

    def resolved_cache_dir(self) -> Path:
        """``cache_dir``, else ``$MMF_RL_CACHE``, else ``~/.cache/mmf_rl``; windows live in ``windows/``."""
        if self.cache_dir is not None:
            return Path(self.cache_dir)
        return Path(os.environ.get("MMF_RL_CACHE", Path.home() / ".cache" / "mmf_rl")) / "windows"


def _indices(values, key: str) -> list[int] | None:
    """``values`` (a list of feature dims) as ints; a scalar, or an entry that is not a whole
    number, is a ValueError naming ``key`` (``int`` alone would cut 1.5 to 1)."""
    if values is None:
        return None
    wrong = ValueError(f"data config: `{key}` must be a list of whole-number indices, found {values!r}")
    if isinstance(values, str | bytes) or not hasattr(values, "__iter__"):
        raise wrong
    indices = []
    for value in values:
        try:
            index = int(value)
        except (TypeError, ValueError):
            raise wrong from None
        if isinstance(value, bool) or index != value:
            raise wrong
        indices.append(index)
    return indices


def _pairs(values, key: str) -> list[list[int]] | None:
    """``values`` (``[x, y]`` index pairs) as lists of ints; anything else is a ValueError naming ``key``."""
    if values is None:
        return None
    if isinstance(values, str | bytes) or not hasattr(values, "__iter__"):
        raise ValueError(f"data config: `{key}` must be a list of [x, y] index pairs, found {values!r}")
    return [_indices(pair, key) for pair in values]


def _entry(cls, value, key: str):
    """One entry of the data config (a modality, the target, the action): a mapping of ``cls``'s
    fields, or just the name of its feature."""
    if isinstance(value, str):
        value = {"feature": value}
    elif isinstance(value, dict) or hasattr(value, "items"):
        value = dict(value)
    else:
        raise ValueError(f"data config: `{key}` must be a feature name or a mapping, found {value!r}")
    reject_unknown_keys(cls, value, f"data config: {key}")
    absent = [
        f.name
        for f in fields(cls)
        if f.default is MISSING and f.default_factory is MISSING and f.name not in value
    ]
    if absent:
        raise ValueError(
            f"data config: `{key}` gives no {', '.join(absent)} (found {value}); give the dataset feature it "
            f"reads, e.g. data.{key}.feature=observation.state"
        )
    return cls(**value)


def _missing_entry(name, value) -> float | OutageConfig:
    """One ``missing`` entry: a fraction of windows, or an outage mapping ``{fraction, mean_burst}``."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, dict) or hasattr(value, "items"):
        value = dict(value)
        reject_unknown_keys(OutageConfig, value, f"data config: missing.{name}")
        return OutageConfig(**value)
    raise ValueError(
        f"data config: `missing.{name}` must be a fraction of windows or {{fraction: f, mean_burst: L}}, "
        f"found {value!r}"
    )
