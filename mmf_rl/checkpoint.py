"""Checkpoints that a kill cannot half-write and that loading cannot turn into code execution.

Layout of one checkpoint (a directory)::

    step_000100/
      model.safetensors     weights (safetensors: tensors only, no pickle)
      tensors.safetensors   other named tensors stored with the run (e.g. normalisation stats)
      trainer_state.pt      optimizer / scheduler / RNG / sampler state, loaded with weights_only=True
      meta.json             step, config, data fingerprint, anything JSON

A checkpoint is written into a temporary sibling directory, flushed, then renamed into place;
the ``last`` file next to it is replaced atomically after that. A reader therefore sees either the
previous checkpoint or the new one, never a partial one. A full disk (``ENOSPC``) is a
`CheckpointError` that says the previous checkpoint is intact; what a kill during a save or a
prune leaves (``.step_*.tmp``, ``.step_*.deleting``, ``.last.tmp``) is removed by
:func:`remove_leftovers` when the run starts again.
"""

from __future__ import annotations

import errno
import json
import os
import pickle
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

MODEL_FILE = "model.safetensors"
TENSORS_FILE = "tensors.safetensors"
TRAINER_STATE_FILE = "trainer_state.pt"
META_FILE = "meta.json"
LAST_POINTER = "last"
FORMAT_VERSION = 1
# What a killed save or prune leaves beside the checkpoints (temp dirs of save_checkpoint).
LEFTOVER_PATTERNS = (".step_*.tmp", ".step_*.deleting", f".{LAST_POINTER}.tmp")


class CheckpointError(RuntimeError):
    """A checkpoint is missing, corrupted, unsafe or does not fit the model it is loaded into."""


@dataclass
class Checkpoint:
    path: Path
    meta: dict
    model_state: dict[str, torch.Tensor]
    tensors: dict[str, torch.Tensor] = field(default_factory=dict)
    trainer_state: dict | None = None

    @property
    def step(self) -> int:
        return int(self.meta["step"])


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _write_json(path: Path, obj) -> None:
    with open(path, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=True)
        f.flush()
        os.fsync(f.fileno())


def save_checkpoint(
    directory: str | os.PathLike,
    step: int,
    model_state: dict[str, torch.Tensor],
    *,
    meta: dict | None = None,
    tensors: dict[str, torch.Tensor] | None = None,
    trainer_state: dict | None = None,
    keep_last: int | None = None,
    point_last: bool = True,
) -> Path:
    """Write checkpoint ``step`` under ``directory`` atomically and point ``last`` at it.

    ``keep_last``: delete all but the newest ``keep_last`` checkpoints afterwards. ``point_last=False``
    leaves ``last`` as it is (re-saving an earlier checkpoint with a change, e.g. its scale factors).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    try:
        final = _save(directory, step, model_state, meta, tensors, trainer_state, point_last)
    except OSError as error:
        if error.errno != errno.ENOSPC:
            raise
        previous = list_checkpoints(directory)
        kept = (
            f"the previous checkpoint {previous[-1]} is intact"
            if previous
            else "no earlier checkpoint exists"
        )
        raise CheckpointError(
            f"no space left on device while saving checkpoint step {step} in {directory} "
            f"({error}); its temporary files were removed and {kept}. Free space, then continue "
            "with resume=true"
        ) from None
    if keep_last is not None:
        for old in list_checkpoints(directory)[:-keep_last]:
            # Out of the step_* names first (rename onto an empty temp dir), so a kill during the
            # delete leaves a hidden leftover, never a step_* checkpoint with files missing.
            trash = tempfile.mkdtemp(prefix=f".{old.name}.", suffix=".deleting", dir=directory)
            os.replace(old, trash)
            shutil.rmtree(trash, ignore_errors=True)
    return final


def _save(
    directory: Path,
    step: int,
    model_state: dict[str, torch.Tensor],
    meta: dict | None,
    tensors: dict[str, torch.Tensor] | None,
    trainer_state: dict | None,
    point_last: bool,
) -> Path:
    final = directory / f"step_{step:09d}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".tmp", dir=directory))
    try:
        # safetensors refuses shared or non-contiguous storage; a state dict may have both.
        save_file({k: v.detach().contiguous().clone() for k, v in model_state.items()}, tmp / MODEL_FILE)
        save_file(
            {k: v.detach().contiguous().clone() for k, v in (tensors or {}).items()}, tmp / TENSORS_FILE
        )
        if trainer_state is not None:
            torch.save(trainer_state, tmp / TRAINER_STATE_FILE)
        _write_json(tmp / META_FILE, {"format_version": FORMAT_VERSION, "step": int(step), **(meta or {})})
        for name in (MODEL_FILE, TENSORS_FILE, TRAINER_STATE_FILE):
            if (tmp / name).exists():
                with open(tmp / name, "rb+") as f:
                    os.fsync(f.fileno())
        replaced = None
        if final.exists():  # re-saving the same step (after a resume, or a calibration): replace it
            # Renamed aside first: a kill never leaves a step_* directory with files missing.
            replaced = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".deleting", dir=directory))
            os.replace(final, replaced)
        os.replace(tmp, final)
        _fsync_dir(directory)
        if replaced is not None:
            shutil.rmtree(replaced, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if not point_last:
        return final
    pointer_tmp = directory / f".{LAST_POINTER}.tmp"
    try:
        pointer_tmp.write_text(final.name + "\n")
        os.replace(pointer_tmp, directory / LAST_POINTER)
    except BaseException:
        pointer_tmp.unlink(missing_ok=True)
        raise
    return final


def remove_leftovers(directory: str | os.PathLike) -> list[Path]:
    """Delete what a killed save or prune left in ``directory`` (never a complete checkpoint);
    return what was removed. Call it when a run starts: no save is in progress then."""
    directory = Path(directory)
    removed = sorted(p for pattern in LEFTOVER_PATTERNS for p in directory.glob(pattern))
    for path in removed:
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    return removed


def list_checkpoints(directory: str | os.PathLike) -> list[Path]:
    """Complete checkpoints under ``directory``, oldest first (temporary directories excluded)."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(p for p in directory.glob("step_*") if p.is_dir() and (p / META_FILE).is_file())


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """A checkpoint directory, or the one a ``last`` pointer names in ``path``."""
    path = Path(path)
    if (path / META_FILE).is_file():
        return path
    pointer = path / LAST_POINTER
    if pointer.is_file():
        target = path / pointer.read_text().strip()
        if (target / META_FILE).is_file():
            return target
        raise CheckpointError(
            f"{pointer} names {target.name}, which is not a complete checkpoint; "
            f"pass one of {[p.name for p in list_checkpoints(path)]} explicitly"
        )
    if not path.exists():
        raise CheckpointError(f"checkpoint not found: {path} does not exist")
    raise CheckpointError(
        f"{path} is neither a checkpoint (no {META_FILE}) nor a directory with a '{LAST_POINTER}' pointer"
    )


def _load_safetensors(path: Path) -> dict[str, torch.Tensor]:
    try:
        return load_file(path)
    except (SafetensorError, OSError, ValueError) as err:
        raise CheckpointError(
            f"cannot read {path}: {err}; the file is corrupted or truncated — use an earlier checkpoint"
        ) from None


def read_meta(path: str | os.PathLike) -> dict:
    """The ``meta.json`` of the checkpoint directory ``path``, checked (step, format version)."""
    path = Path(path)
    try:
        meta = json.loads((path / META_FILE).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise CheckpointError(f"cannot read {path / META_FILE}: {err}") from None
    if not isinstance(meta, dict) or "step" not in meta:
        raise CheckpointError(f"{path / META_FILE} is not an mmf-rl checkpoint description (no 'step')")
    if meta.get("format_version", 0) > FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format {meta['format_version']}, newer than this mmf-rl "
            f"reads ({FORMAT_VERSION}); upgrade mmf-rl"
        )
    return meta


def load_checkpoint(path: str | os.PathLike, *, with_trainer_state: bool = True) -> Checkpoint:
    """Read a checkpoint (or the ``last`` one in a directory) without executing any code."""
    path = resolve_checkpoint(path)
    meta = read_meta(path)
    model_state = _load_safetensors(path / MODEL_FILE)
    tensors = _load_safetensors(path / TENSORS_FILE) if (path / TENSORS_FILE).exists() else {}
    trainer_state = None
    state_file = path / TRAINER_STATE_FILE
    if with_trainer_state and state_file.exists():
        try:
            trainer_state = torch.load(state_file, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError as err:
            raise CheckpointError(
                f"refusing to load {state_file}: it holds objects other than tensors and plain "
                f"containers ({str(err).splitlines()[0]}); only trusted, plain state is loaded"
            ) from None
        except (RuntimeError, EOFError, OSError) as err:
            raise CheckpointError(
                f"cannot read {state_file}: {err}; the file is corrupted or truncated"
            ) from None
    return Checkpoint(
        path=path, meta=meta, model_state=model_state, tensors=tensors, trainer_state=trainer_state
    )


def state_mismatch(own: dict[str, torch.Tensor], loaded: dict[str, torch.Tensor]) -> str | None:
    """What differs between a model's state dict and a loaded one (missing, unexpected, shapes).

    None if nothing.
    """
    missing = sorted(set(own) - set(loaded))
    unexpected = sorted(set(loaded) - set(own))
    mismatched = [
        f"{k}: expected {list(v.shape)}, found {list(loaded[k].shape)}"
        for k, v in own.items()
        if k in loaded and loaded[k].shape != v.shape
    ]
    details = []
    if missing:
        details.append(f"missing: {missing[:5]}{' ...' if len(missing) > 5 else ''}")
    if unexpected:
        details.append(f"not in the model: {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
    if mismatched:
        details.append(
            f"shape mismatch (model vs saved): {mismatched[:5]}{' ...' if len(mismatched) > 5 else ''}"
        )
    return "; ".join(details) or None


def known_mismatch(module: torch.nn.Module, loaded: dict[str, torch.Tensor]) -> str | None:
    """Why ``loaded`` does not fit ``module``, if the module knows: a model may define
    ``explain_state_mismatch(loaded) -> str | None`` for weights it can recognise, e.g. ones saved by
    an older version of it, whose fix is not "use the checkpoint's own config"."""
    explain = getattr(module, "explain_state_mismatch", None)
    return explain(loaded) if explain is not None else None


def state_with_defaults(module: torch.nn.Module, loaded: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``loaded`` completed with the entries a state saved before they existed lacks.

    Any submodule may define ``state_defaults() -> dict[str, Tensor]`` (names relative to it): the
    value under which the module behaves as it did before the entry existed (e.g. scale factors of
    ones). Only such entries are filled in; every other missing weight stays a mismatch."""
    completed = dict(loaded)
    for prefix, submodule in module.named_modules():
        defaults = getattr(submodule, "state_defaults", None)
        if callable(defaults):
            for name, value in defaults().items():
                completed.setdefault(f"{prefix}.{name}" if prefix else name, value)
    return completed


def load_model_state(module: torch.nn.Module, checkpoint: Checkpoint) -> None:
    """Load weights strictly (completed by :func:`state_with_defaults`); a mismatch names the keys
    and shapes on both sides."""
    state = state_with_defaults(module, checkpoint.model_state)
    mismatch = state_mismatch(module.state_dict(), state)
    if mismatch:
        known = known_mismatch(module, checkpoint.model_state)
        if known:
            raise CheckpointError(f"{checkpoint.path} does not fit this model ({mismatch}): {known}")
        raise CheckpointError(
            f"{checkpoint.path} was saved from a different model configuration ({mismatch}); "
            f"build the model from the checkpoint's own config ({META_FILE} 'config')"
        )
    module.load_state_dict(state)
