"""Unimodal encoders ``E_m``: one modality's window -> ``d``-tokens per sample.

Most encoders summarise the window in one token ``[N, d]``. A step-token encoder keeps the
detail of every step: it sets ``num_tokens`` (``L``) and returns ``[N, L, d]`` with a learned step
embedding, and the multimodal encoder attends over every present token (the fixed queries keep
its output shape).

Encoders are registered by name: a new one is a class (or builder) here, or in user code,
plus one ``@register_encoder(name, kinds)``; a :class:`~mmf_rl.keys.ModalitySpec` then names it
in ``encoder`` (a data config's ``modalities.<m>.encoder``), and every model that encodes
whole windows builds it through :func:`build_encoder`.

With ``("present_steps", m)`` the forecaster zeroes a window's absent steps before any encoder
reads them. A step-token encoder (``tokens_are_steps``: ``steps``, ``conv_frames``) then has the
tokens of those steps masked out of attention. A whole-window encoder (``mlp``, ``gru``, ``conv``,
``conv_gru``, ``conv_patches``, ``deepsets``, ``set_attention``) sees the zeroed steps only: its input
layout has no slot for a step mask without changing its weights' shapes (and so every saved
checkpoint).

No BatchNorm anywhere: the forecaster encodes only the samples where a modality is present,
and batch statistics would make one sample's output depend on which others are present.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Literal

import torch
from torch import nn

from mmf_rl.keys import DEFAULT_ENCODER, MODALITY_KINDS, ModalitySpec

# build(spec, history, d_model, **spec.encoder_kwargs) -> a module mapping one modality's
# observation [N, *spec.obs_shape(history)] to [N, d_model].
EncoderBuilder = Callable[..., nn.Module]


@dataclass(frozen=True)
class EncoderEntry:
    kinds: tuple[str, ...]
    build: EncoderBuilder


ENCODERS: dict[str, EncoderEntry] = {}


def register_encoder(name: str, kinds: tuple[str, ...]) -> Callable[[EncoderBuilder], EncoderBuilder]:
    """Register ``build(spec, history, d_model, **encoder_kwargs)`` as encoder ``name`` for ``kinds``."""
    unknown = sorted(set(kinds) - set(MODALITY_KINDS))
    if not kinds or unknown:
        raise ValueError(
            f"encoder {name!r}: kinds must be a non-empty subset of {MODALITY_KINDS}, found {kinds}"
        )

    def register(build: EncoderBuilder) -> EncoderBuilder:
        if name in ENCODERS:
            raise ValueError(f"encoder {name!r} is already registered (for kinds {ENCODERS[name].kinds})")
        ENCODERS[name] = EncoderEntry(tuple(kinds), build)
        return build

    return register


def encoders_for(kind: str) -> list[str]:
    """The names of the encoders registered for modalities of ``kind``."""
    return sorted(name for name, entry in ENCODERS.items() if kind in entry.kinds)


def check_encoder(modality: str, encoder: str, kind: str | None) -> EncoderEntry:
    """The registry entry of ``encoder`` for ``modality`` of ``kind``; a clear error if none fits.

    ``kind=None`` checks the name only (a data config, before the dataset's features fix the kind).
    """
    entry = ENCODERS.get(encoder)
    if entry is not None and (kind is None or kind in entry.kinds):
        return entry
    what = f"modality {modality!r}" + (f" ({kind})" if kind else "")
    hint = (
        ""
        if entry is not None
        else ("; a new encoder is registered with @mmf_rl.models.encoders.register_encoder(name, kinds)")
    )
    expected = f"{encoders_for(kind)} (default {DEFAULT_ENCODER[kind]!r})" if kind else sorted(ENCODERS)
    raise ValueError(f"{what}: encoder {encoder!r} is not available; expected one of {expected}{hint}")


def mlp(in_dim: int, hidden_dim: int, out_dim: int) -> nn.Sequential:
    """Two linear layers with a ReLU between them (the paper's MLP blocks)."""
    return nn.Sequential(nn.Linear(in_dim, hidden_dim), nn.ReLU(), nn.Linear(hidden_dim, out_dim))


def _conv_trunk(in_channels: int, channels: tuple[int, ...]) -> nn.Sequential:
    # Stride-2 4x4 convolutions halve the resolution each layer; GroupNorm keeps training
    # stable without batch statistics.
    layers: list[nn.Module] = []
    for out in channels:
        layers += [
            nn.Conv2d(in_channels, out, 4, stride=2, padding=1),
            nn.GroupNorm(min(8, out), out),
            nn.ReLU(),
        ]
        in_channels = out
    return nn.Sequential(*layers)


class ImageWindowEncoder(nn.Module):
    """ConvNet for a window of frames ``uint8 [N, H, C, h, w]`` -> ``[N, d]``.

    ``temporal="stack"``: the ``H`` frames are stacked on the channel axis and go through one
    ConvNet, so motion is visible to the first layer and the cost is one image per sample
    instead of ``H``. ``temporal="gru"``: a ConvNet per frame, then a GRU over the frame
    features (``H`` times the convolution cost).
    """

    def __init__(
        self,
        spec: ModalitySpec,
        history: int,
        d_model: int,
        channels: tuple[int, ...] = (32, 64, 64, 64),
        temporal: str = "stack",
    ):
        super().__init__()
        c, h, w = spec.shape
        if not channels:
            raise ValueError(
                f"image encoder for {spec.name!r}: channels is empty; give the width of each stride-2 "
                "convolution, e.g. encoder_kwargs.channels=[32, 64, 64, 64]"
            )
        if temporal not in ("stack", "gru"):
            raise ValueError(
                f"image encoder for {spec.name!r}: temporal must be 'stack' or 'gru', found {temporal!r}"
            )
        self.temporal = temporal
        in_channels = c * history if temporal == "stack" else c
        self.trunk = _conv_trunk(in_channels, tuple(channels))
        reduce = 2 ** len(channels)
        if h % reduce or w % reduce:
            raise ValueError(
                f"image encoder for {spec.name!r}: image size {h}x{w} must be divisible by {reduce} "
                f"({len(channels)} stride-2 layers); resize the images or change encoder channels"
            )
        flat = channels[-1] * (h // reduce) * (w // reduce)
        self.project = nn.Linear(flat, d_model)
        self.gru = nn.GRU(d_model, d_model, batch_first=True) if temporal == "gru" else None

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        n, hist = frames.shape[:2]
        # uint8 [0, 255] -> float [-0.5, 0.5]
        x = frames.float().mul_(1.0 / 255.0).sub_(0.5)
        if self.temporal == "stack":
            x = x.flatten(1, 2)
            return self.project(self.trunk(x).flatten(1))
        feats = self.project(self.trunk(x.flatten(0, 1)).flatten(1)).view(n, hist, -1)
        return self.gru(torch.relu(feats))[1][-1]


@register_encoder("conv", kinds=("image",))
def conv_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> ImageWindowEncoder:
    return ImageWindowEncoder(spec, history, d_model, temporal="stack", **kwargs)


@register_encoder("conv_gru", kinds=("image",))
def conv_gru_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> ImageWindowEncoder:
    return ImageWindowEncoder(spec, history, d_model, temporal="gru", **kwargs)


class SequenceGRUEncoder(nn.Module):
    """GRU over a window of vectors ``[N, H, d_in]`` -> last hidden state ``[N, d]``."""

    def __init__(self, spec: ModalitySpec, d_model: int, num_layers: int = 1):
        super().__init__()
        self.embed = nn.Linear(spec.shape[0], d_model)
        self.gru = nn.GRU(d_model, d_model, num_layers=num_layers, batch_first=True)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        return self.gru(torch.relu(self.embed(seq)))[1][-1]


@register_encoder("gru", kinds=("sequence",))
def gru_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> SequenceGRUEncoder:
    return SequenceGRUEncoder(spec, d_model, **kwargs)


class FlatMLPEncoder(nn.Module):
    """MLP over a single vector ``[N, d_in]`` or a flattened window ``[N, H, d_in]``."""

    def __init__(self, in_dim: int, d_model: int, hidden_dim: int | None = None):
        super().__init__()
        self.net = mlp(in_dim, hidden_dim or 2 * d_model, d_model)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.flatten(1))


class StepTokens(nn.Module):
    """One token per step of a vector window ``[N, H, d_in]`` -> ``[N, H, d]``: a per-step MLP plus a
    learned step embedding (so attention can tell the steps apart, as MulT's tokens do).
    ``per_step="linear"``: a linear layer + ReLU per step instead of the MLP (MulT's tokenizer)."""

    # One token per step: an absent step (``("present_steps", m)``) is an absent token.
    tokens_are_steps = True

    def __init__(
        self,
        spec: ModalitySpec,
        history: int,
        d_model: int,
        hidden_dim: int | None = None,
        per_step: Literal["mlp", "linear"] = "mlp",
    ):
        super().__init__()
        if per_step not in ("mlp", "linear"):
            raise ValueError(
                f"the step encoder of {spec.name!r}: per_step must be 'mlp' or 'linear', found {per_step!r}"
            )
        self.num_tokens = history
        self.net = (
            mlp(spec.shape[0], hidden_dim or 2 * d_model, d_model)
            if per_step == "mlp"
            else nn.Sequential(nn.Linear(spec.shape[0], d_model), nn.ReLU())
        )
        self.step_embedding = nn.Parameter(torch.randn(history, d_model) * 0.02)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        return self.net(seq) + self.step_embedding


@register_encoder("steps", kinds=("sequence",))
def steps_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> StepTokens:
    return StepTokens(spec, history, d_model, **kwargs)


@register_encoder("linear_steps", kinds=("sequence",))
def linear_steps_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> StepTokens:
    """MulT's tokenizer: a linear layer + ReLU per step (and the step embedding)."""
    return StepTokens(spec, history, d_model, per_step="linear", **kwargs)


class FrameTokens(nn.Module):
    """One token per frame of an image window ``uint8 [N, H, C, h, w]`` -> ``[N, H, d]``: the
    ConvNet on each frame plus a learned step embedding (``H`` times the cost of ``conv``)."""

    # One token per step: an absent step (``("present_steps", m)``) is an absent token.
    tokens_are_steps = True

    def __init__(self, spec: ModalitySpec, history: int, d_model: int, **kwargs):
        super().__init__()
        self.num_tokens = history
        self.frame = ImageWindowEncoder(spec, 1, d_model, temporal="stack", **kwargs)
        self.step_embedding = nn.Parameter(torch.randn(history, d_model) * 0.02)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        n, steps = frames.shape[:2]
        return self.frame(frames.flatten(0, 1).unsqueeze(1)).view(n, steps, -1) + self.step_embedding


@register_encoder("conv_frames", kinds=("image",))
def conv_frames_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> FrameTokens:
    return FrameTokens(spec, history, d_model, **kwargs)


class PatchTokens(nn.Module):
    """The frame-stacked ConvNet of ``conv``, one token per cell of its last feature map (plus a
    learned position embedding) instead of one projection of the whole map: spatial detail at the
    cost of ``conv``, ``(h / 2^L) × (w / 2^L)`` tokens."""

    def __init__(self, spec: ModalitySpec, history: int, d_model: int, **kwargs):
        super().__init__()
        stack = ImageWindowEncoder(spec, history, d_model, temporal="stack", **kwargs)
        self.trunk = stack.trunk
        channels = next(m for m in reversed(self.trunk) if isinstance(m, nn.Conv2d)).out_channels
        cells = stack.project.in_features // channels
        self.num_tokens = cells
        self.project = nn.Linear(channels, d_model)
        self.position_embedding = nn.Parameter(torch.randn(cells, d_model) * 0.02)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        x = frames.float().mul_(1.0 / 255.0).sub_(0.5).flatten(1, 2)
        cells = self.trunk(x).flatten(2).transpose(1, 2)  # [N, cells, channels]
        return self.project(cells) + self.position_embedding


@register_encoder("conv_patches", kinds=("image",))
def conv_patches_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> PatchTokens:
    return PatchTokens(spec, history, d_model, **kwargs)


def num_tokens(encoder: nn.Module) -> int:
    """Tokens an encoder emits per sample: ``num_tokens`` if it declares one (``[N, L, d]``), else 1
    (``[N, d]``)."""
    return getattr(encoder, "num_tokens", 1)


@register_encoder("mlp", kinds=("sequence", "vector"))
def mlp_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> FlatMLPEncoder:
    in_dim = spec.shape[0] * (1 if spec.kind == "vector" else history)
    return FlatMLPEncoder(in_dim, d_model, **kwargs)


class _AgentSlots(nn.Module):
    """Base of the encoders of a window of agent slots ``[N, H, K * slot_dim]``: each step holds ``K``
    slots of ``slot_dim`` values whose last one is the slot's validity (1 = an agent, 0 = an empty slot,
    left unnormalised by the data config's ``raw_dims``)."""

    def __init__(self, spec: ModalitySpec, slot_dim: int, encoder: str):
        super().__init__()
        if slot_dim < 2 or spec.shape[0] % slot_dim:
            raise ValueError(
                f"{encoder} encoder for {spec.name!r}: the feature's {spec.shape[0]} dims must be K slots of "
                f"slot_dim={slot_dim} values (the last one the validity); set the data config's "
                f"modalities.{spec.name}.encoder_kwargs.slot_dim"
            )
        self.slot_dim = slot_dim

    def slots(self, seq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The slots' values ``[N, H, K, slot_dim - 1]`` (zeros in empty slots, so they are never read)
        and validity ``bool [N, H, K, 1]``."""
        slots = seq.unflatten(-1, (-1, self.slot_dim))
        valid = slots[..., -1:] > 0.5
        return torch.where(valid, slots[..., :-1], torch.zeros_like(slots[..., :-1])), valid


class DeepSetsEncoder(_AgentSlots):
    """Slot-order-invariant encoder of a window of agent slots ``[N, H, K * slot_dim]`` -> ``[N, d]``.

    A shared MLP embeds every slot; a masked mean and max over the valid slots pool each step
    (DeepSets), so permuting slots changes nothing and an empty slot's values are never read; a
    step without any valid slot pools to zeros. A GRU then summarises the steps.
    """

    def __init__(self, spec: ModalitySpec, d_model: int, slot_dim: int = 5, hidden_dim: int | None = None):
        super().__init__(spec, slot_dim, "deepsets")
        hidden = hidden_dim or d_model
        self.slot = mlp(slot_dim - 1, hidden, hidden)
        self.step = nn.Linear(2 * hidden, d_model)
        self.gru = nn.GRU(d_model, d_model, batch_first=True)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        values, valid = self.slots(seq)
        embedded = self.slot(values)
        count = valid.sum(-2)
        mean = (embedded * valid).sum(-2) / count.clamp_min(1)
        peak = embedded.masked_fill(~valid, float("-inf")).amax(-2)
        peak = torch.where(count > 0, peak, torch.zeros_like(peak))
        steps = torch.relu(self.step(torch.cat([mean, peak], -1)))
        return self.gru(steps)[1][-1]


@register_encoder("deepsets", kinds=("sequence",))
def deepsets_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> DeepSetsEncoder:
    return DeepSetsEncoder(spec, d_model, **kwargs)


class SetAttentionEncoder(_AgentSlots):
    """Slot-order-invariant encoder of a window of agent slots ``[N, H, K * slot_dim]`` -> ``[N, d]``
    that weighs the agents by what they do: at each step the valid slots attend to each other (one
    Transformer layer), then a learned query pools them by attention (Set Transformer's PMA, Lee et al.
    2019), so one agent on a collision course can outweigh many that walk away, where a mean dilutes it.
    A learned "nobody" token is always among the keys: a step without any valid slot pools to it,
    never to the values of empty slots. A GRU then summarises the steps.
    """

    def __init__(
        self,
        spec: ModalitySpec,
        d_model: int,
        slot_dim: int = 5,
        hidden_dim: int | None = None,
        num_heads: int = 4,
    ):
        super().__init__(spec, slot_dim, "set_attention")
        self.slot = mlp(slot_dim - 1, hidden_dim or d_model, d_model)
        self.nobody = nn.Parameter(torch.randn(1, 1, d_model) * 0.02)
        self.mix = nn.TransformerEncoderLayer(
            d_model, num_heads, dim_feedforward=2 * d_model, dropout=0.0, batch_first=True
        )
        self.query = nn.Parameter(torch.randn(1, 1, d_model) * 0.02)
        self.pool = nn.MultiheadAttention(d_model, num_heads, batch_first=True)
        self.gru = nn.GRU(d_model, d_model, batch_first=True)

    def forward(self, seq: torch.Tensor) -> torch.Tensor:
        values, valid = self.slots(seq)
        n, steps = values.shape[:2]
        embedded = self.slot(values).flatten(0, 1)  # [N * H, K, d]
        tokens = torch.cat([self.nobody.expand(len(embedded), -1, -1), embedded], 1)
        ignored = torch.cat([valid.new_zeros(len(embedded), 1), ~valid.flatten(0, 1)[..., 0]], 1)
        mixed = self.mix(tokens, src_key_padding_mask=ignored)
        query = self.query.expand(len(mixed), -1, -1)
        pooled = self.pool(query, mixed, mixed, key_padding_mask=ignored, need_weights=False)[0]
        return self.gru(pooled.view(n, steps, -1))[1][-1]


@register_encoder("set_attention", kinds=("sequence",))
def set_attention_encoder(spec: ModalitySpec, history: int, d_model: int, **kwargs) -> SetAttentionEncoder:
    return SetAttentionEncoder(spec, d_model, **kwargs)


def build_encoder(spec: ModalitySpec, history: int, d_model: int) -> nn.Module:
    """The registered encoder a spec names, with its ``encoder_kwargs``."""
    entry = check_encoder(spec.name, spec.encoder, spec.kind)
    build = partial(entry.build, spec, history, d_model)
    return with_encoder_kwargs(spec, build, f"encoder {spec.encoder!r}")


def with_encoder_kwargs(spec: ModalitySpec, build: Callable[..., nn.Module], what: str) -> nn.Module:
    """``build(**spec.encoder_kwargs)``; a keyword ``build`` does not take is a ``ValueError`` naming the
    modality, its ``encoder_kwargs`` and ``what`` they were given to, not a ``TypeError`` from a
    constructor."""
    kwargs = dict(spec.encoder_kwargs)
    try:
        return build(**kwargs)
    except TypeError as err:
        raise ValueError(f"modality {spec.name!r}: bad encoder_kwargs {kwargs} for {what}: {err}") from None
