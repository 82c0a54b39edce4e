"""Hydra configs: compose ``configs/<name>.yaml`` with command-line overrides, save them atomically."""

from __future__ import annotations

import os
from dataclasses import fields
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

# The repository's configs/ (editable install); MMF_RL_CONFIG_DIR points elsewhere.
DEFAULT_CONFIG_DIR = Path(__file__).resolve().parents[1] / "configs"


class ConfigError(ValueError):
    """A config could not be composed: unknown key, unknown option, bad value."""


def config_dir() -> Path:
    path = Path(os.environ.get("MMF_RL_CONFIG_DIR", DEFAULT_CONFIG_DIR))
    if not (path / "train.yaml").is_file():
        raise ConfigError(f"no mmf-rl configs in {path} (train.yaml missing); set MMF_RL_CONFIG_DIR to the "
                          "repository's configs/ directory")
    return path


def reject_unknown_keys(cls, d: dict, where: str) -> None:
    """A dataclass config built from plain data: name any key it does not have, and what it has."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown}; expected a subset of {sorted(known)}")


def compose_config(name: str, overrides: list[str]) -> DictConfig:
    """``configs/<name>.yaml`` + ``key=value`` / ``group=option`` overrides, resolved, struct mode."""
    # Imported here: models and datasets import this module for reject_unknown_keys only.
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(config_name=name, overrides=list(overrides))
        OmegaConf.resolve(cfg)
    except (HydraException, OmegaConfBaseException) as err:
        # Hydra's messages name the key and the options; its chained causes add only noise.
        raise ConfigError(str(err).strip()) from None
    return cfg


def to_container(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg, resolve=True)


def save_config(cfg: DictConfig | dict, path: Path) -> None:
    """Write YAML atomically (temp file + rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(OmegaConf.to_yaml(cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)))
    os.replace(tmp, path)


def load_config(path: Path) -> DictConfig:
    return OmegaConf.load(path)
