"""Hydra configs: compose ``configs/<name>.yaml`` with command-line overrides, save them atomically.

Three things are added on top of Hydra's compose API, all decided here so every command behaves
the same:

* A mapping given whole on the command line replaces the config's (``data.modalities='{cam:
  observation.images.top}'``), where Hydra would merge it into the base config's mapping. The keys
  are :data:`REPLACED_MAPPINGS`; a dotted key (``data.modalities.cam.required=true``) still edits
  one entry, whether or not the entry gives that key yet: the keys of an entry (:data:`ENTRIES`: a
  modality, the target, the action, an outage) all have defaults in the data config, and an entry
  given as a feature name (``cam: observation.images.top``) is short for ``{feature: ...}``.
  Hydra alone refuses such an edit: it composes in struct mode, where ``key=value`` may only
  change a key that exists and adding one takes ``+key=value`` (its override grammar). So the
  overrides of these mappings are applied here, after Hydra has composed the rest (group options
  included), in command-line order, with Hydra's own parsed values; the entry they edit must
  exist (a misspelt modality is an error naming the ones there are).
* Config files outside the package: ``config_dirs`` are added to Hydra's search path (their
  ``<group>/<name>.yaml`` become options of ``<group>``), and a group option may be a YAML file's
  path (``data=/path/to/mine.yaml``).
* ``mmf-rl <command> --help`` lists the config groups and their options, ``--cfg`` prints the
  composed config (see :func:`run_config_command`, the skeleton of every such command).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import ClassVar, Self, TypeVar

from omegaconf import DictConfig, OmegaConf, open_dict

# The configs shipped inside the package (a link to the repository's configs/ in a checkout, a
# copy in a wheel); MMF_RL_CONFIG_DIR points elsewhere.
DEFAULT_CONFIG_DIR = (Path(__file__).parent / "configs").resolve()
# Mappings that a whole value on the command line replaces instead of merging into.
REPLACED_MAPPINGS = ("data.modalities", "data.target", "data.missing", "data.action")
# Their entries, whose keys all have defaults (ModalityConfig, TargetConfig, ActionConfig,
# OutageConfig): a dotted override sets one whether or not the entry gives it.
ENTRIES = ("data.modalities.*", "data.target", "data.action", "data.missing.*")
YAML_SUFFIXES = (".yaml", ".yml")
T = TypeVar("T")


class ConfigError(ValueError):
    """A config could not be composed: unknown key, unknown option, bad value."""


def config_dir() -> Path:
    """The directory of the built-in configs: ``MMF_RL_CONFIG_DIR`` if set, else the package's.

    Returns:
        The directory holding ``train.yaml`` and the config groups.

    Raises:
        ConfigError: the directory has no ``train.yaml``.
    """
    path = Path(os.environ.get("MMF_RL_CONFIG_DIR", DEFAULT_CONFIG_DIR))
    if not (path / "train.yaml").is_file():
        raise ConfigError(
            f"no mmf-rl configs in {path} (train.yaml missing); unset MMF_RL_CONFIG_DIR to use the "
            f"configs installed with mmf-rl ({DEFAULT_CONFIG_DIR}), or point it at a copy of them"
        )
    return path


def reject_unknown_keys(cls, d: dict, where: str) -> None:
    """Refuse plain data with keys a dataclass config does not have, naming them and the known ones.

    Args:
        cls (type): the dataclass.
        d (dict): the plain data it is about to be built from.
        where (str): what the error message calls the config (e.g. ``"ForecasterConfig"``).

    Raises:
        ValueError: ``d`` has a key that is not a field of ``cls``.
    """
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ValueError(f"{where}: unknown keys {unknown}; expected a subset of {sorted(known)}")


class SavedConfigMixin:
    """A dataclass config read from plain data, fresh or saved with a model: :meth:`from_dict` and
    :meth:`from_saved_dict` (the model configs, :class:`~mmf_rl.models.ForecasterConfig` and the
    baselines' :class:`~mmf_rl.models.baselines.common.BaselineConfig`).

    ``SAVED_BEFORE`` (a class attribute): the settings a saved config may lack because they did not
    exist when it was saved, and the value that describes the model saved then (not today's default).
    """

    SAVED_BEFORE: ClassVar[dict[str, object]] = {}

    @classmethod
    def from_dict(cls, d: dict) -> Self:
        """Build from plain data: the settings given, today's defaults for the others (a Hydra model
        config, a config written by hand).

        Args:
            d (dict): the fields (modalities as :class:`~mmf_rl.keys.ModalitySpec` or their dicts).

        Returns:
            The config.

        Raises:
            ValueError: an unknown key or an invalid value.
        """
        reject_unknown_keys(cls, d, cls.__name__)
        return cls(**d)

    @classmethod
    def from_saved_dict(cls, d: dict) -> Self:
        """Build from a saved model's config (a checkpoint's ``model_config``, a ``config.json``): a
        setting it lacks did not exist when it was saved, and takes the value :attr:`SAVED_BEFORE`
        gives it, the one that describes the model saved then, not today's default.

        Args:
            d (dict): the saved fields (the config's ``to_dict`` form).

        Returns:
            The config of the saved model.

        Raises:
            ValueError: an unknown key or an invalid value.
        """
        return cls.from_dict({**cls.SAVED_BEFORE, **d})


def config_groups(config_dirs: list[Path] = ()) -> dict[str, list[str]]:
    """The config groups and their options, built in and in the user's directories.

    Args:
        config_dirs (list[Path], optional): more directories of ``<group>/<name>.yaml`` files.

    Returns:
        ``{group: [option, ...]}``, both sorted.
    """
    groups: dict[str, set[str]] = {}
    for directory in [config_dir(), *config_dirs]:
        for path in Path(directory).glob("*/*"):
            if path.suffix in YAML_SUFFIXES:
                groups.setdefault(path.parent.name, set()).add(path.stem)
    return {group: sorted(options) for group, options in sorted(groups.items())}


def _check_config_dirs(config_dirs: list[Path]) -> list[Path]:
    """The user's config directories, resolved; one that shadows a built-in config is an error
    (Hydra would silently use the built-in one)."""
    builtin = config_dir()
    resolved = []
    for directory in config_dirs:
        directory = Path(directory).expanduser().resolve()
        if not directory.is_dir():
            raise ConfigError(
                f"--config-dir {directory}: no such directory; it should hold <group>/<name>.yaml files "
                "(e.g. data/mine.yaml, used as data=mine)"
            )
        for path in sorted(directory.rglob("*")):
            relative = path.relative_to(directory)
            if path.suffix in YAML_SUFFIXES and (builtin / relative).with_suffix(".yaml").is_file():
                raise ConfigError(
                    f"{path} has the name of mmf-rl's own {builtin / relative.with_suffix('.yaml')}, which "
                    f"Hydra would use instead; rename yours (e.g. {relative.parent / ('my_' + path.name)})"
                )
        resolved.append(directory)
    return resolved


def _config_file_option(group: str, value: str) -> str:
    """Register the YAML file ``value`` as an option of ``group`` (Hydra's ConfigStore) and return
    its option name: Hydra itself takes group options only by name from its search path."""
    from hydra.core.config_store import ConfigStore

    path = Path(value).expanduser().resolve()
    if not path.is_file():
        raise ConfigError(
            f"{group}={value}: no such file ({path}); give the path of a YAML config file, or an option "
            f"name of the `{group}` group (`mmf-rl train --help` lists them)"
        )
    text = path.read_text()
    try:
        node = OmegaConf.create(text)
    except Exception as error:  # noqa: BLE001 - yaml and OmegaConf raise many types; name the file
        raise ConfigError(f"{path}: not a valid YAML config ({' '.join(str(error).split())})") from None
    if not isinstance(node, DictConfig):
        raise ConfigError(f"{path}: a config file must hold a mapping of keys, found {type(node).__name__}")
    header = re.search(r"^#\s*@package\s+(\S+)", text, re.MULTILINE)
    name = (
        f"file_{hashlib.sha1(str(path).encode()).hexdigest()[:8]}_{re.sub(r'[^A-Za-z0-9_]', '_', path.stem)}"
    )
    ConfigStore.instance().store(group=group, name=name, node=node, package=header[1] if header else None)
    return name


def _prepare_overrides(overrides: list[str], config_dirs: list[Path]) -> tuple[list[str], list]:
    """The overrides for Hydra (file-path options registered by name), and the parsed overrides of
    :data:`REPLACED_MAPPINGS` and their keys, which :func:`_apply_mapping_overrides` applies."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import OverrideType
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides))
    except HydraException as err:
        raise ConfigError(str(err).strip()) from None
    groups = config_groups(config_dirs)
    for_hydra, for_mappings = [], []
    for override in parsed:
        key, line = override.key_or_group, override.input_line
        value = override.value()
        if key.startswith(tuple(f"{m}." for m in REPLACED_MAPPINGS)) or key in REPLACED_MAPPINGS:
            for_mappings.append(override)
            continue
        if (
            override.type == OverrideType.CHANGE
            and key in groups
            and isinstance(value, str)
            and value.endswith(YAML_SUFFIXES)
        ):
            line = f"{override.get_key_element()}={_config_file_option(key, value)}"
        for_hydra.append(line)
    return for_hydra, for_mappings


def _is_entry(path: str) -> bool:
    parts = path.split(".")
    return any(
        len(parts) == len(pattern.split("."))
        and all(p == q or q == "*" for p, q in zip(parts, pattern.split("."), strict=True))
        for pattern in ENTRIES
    )


_ABSENT = object()


def _apply_mapping_overrides(cfg: DictConfig, overrides: list) -> None:
    """Apply the overrides of :data:`REPLACED_MAPPINGS` and their keys to the composed ``cfg``, in
    order: a whole mapping replaces the config's; a key of an entry is set whether or not the entry
    gives it (a feature-name entry becomes ``{feature: name}`` first); anything else follows Hydra's
    rules (``key=value`` changes a key that exists, ``+`` adds one, ``++`` either, ``~`` deletes).

    Hand-written because Hydra's rules differ on both points: its ``key=value`` merges a mapping into
    the config's, and its struct mode refuses a key the entry does not give yet. The values are
    Hydra's parsed ones."""
    for override in overrides:
        key, value, line = override.key_or_group, override.value(), override.input_line
        parent, _, leaf = key.rpartition(".")
        current = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=False)
        with open_dict(cfg):
            if override.is_delete():
                if current is _ABSENT or (value is not None and value != current):
                    found = "is not in the config" if current is _ABSENT else f"is {current!r}, not {value!r}"
                    raise ConfigError(f"{line}: {key} {found}; nothing to delete")
                del OmegaConf.select(cfg, parent)[leaf]
            elif key in REPLACED_MAPPINGS:
                OmegaConf.update(cfg, key, value, merge=False, force_add=True)
            elif _is_entry(parent):
                _expand_entry(cfg, parent, line, adding=override.is_add() or override.is_force_add())
                OmegaConf.update(cfg, key, value, merge=True, force_add=True)
            elif override.is_add() and current is not _ABSENT and not isinstance(value, (dict, list)):
                raise ConfigError(
                    f"{line}: {key} is already in the config; change it with {line[1:]} "
                    f"(or add-or-change with +{line})"
                )
            elif not (override.is_add() or override.is_force_add()) and current is _ABSENT:
                node = OmegaConf.select(cfg, parent)
                there = (
                    f" (it has {', '.join(map(str, node)) or 'nothing'})"
                    if isinstance(node, DictConfig)
                    else ""
                )
                raise ConfigError(
                    f"{line}: {parent} has no {leaf!r}{there}; fix the name, or add it with +{line}"
                )
            else:
                OmegaConf.update(cfg, key, value, merge=True, force_add=True)


def _expand_entry(cfg: DictConfig, entry: str, line: str, adding: bool) -> None:
    """Make the entry ``entry`` a mapping a key can be set in: a feature name ``s`` becomes
    ``{feature: s}``; an entry that is not there is an error unless the override adds it."""
    node = OmegaConf.select(cfg, entry, default=_ABSENT, throw_on_missing=False)
    if node is _ABSENT or node is None:
        if adding:
            return
        mapping, _, name = entry.rpartition(".")
        names = OmegaConf.select(cfg, mapping)
        names = ", ".join(str(k) for k in names) if isinstance(names, DictConfig) and names else "none"
        if _is_entry(f"{mapping}.*"):
            where = f"{mapping} has no entry {name!r} (it has {names})"
        else:
            where = f"{entry} is not set"
        raise ConfigError(f"{line}: {where}; fix the name, or give the whole entry: +{entry}='{{...}}'")
    if isinstance(node, str):
        OmegaConf.update(cfg, entry, {"feature": node}, merge=False)
    elif not isinstance(node, DictConfig):
        raise ConfigError(
            f"{line}: {entry} is {node!r}, not a mapping; give the whole entry: {entry}='{{...}}'"
        )


def _compose(name: str, overrides: list[str], config_dirs: list[Path]) -> DictConfig:
    from hydra import compose, initialize_config_dir

    search_path = (
        [f"hydra.searchpath=[{','.join(f'file://{d}' for d in config_dirs)}]"] if config_dirs else []
    )
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        return compose(config_name=name, overrides=search_path + list(overrides))


def compose_config(name: str, overrides: list[str], config_dirs: list[Path] = ()) -> DictConfig:
    """Compose ``configs/<name>.yaml`` with command-line overrides (see the module docstring).

    Args:
        name (str): the config's name (``"train"``, ``"eval"``, ``"calibrate"``).
        overrides (list[str]): ``key=value`` / ``group=option`` / ``+key=value`` overrides, Hydra's
            grammar, applied in order.
        config_dirs (list[Path], optional): more directories of ``<group>/<name>.yaml`` files
            (``--config-dir``).

    Returns:
        The composed config, resolved, in struct mode.

    Raises:
        ConfigError: an unknown key or option, a bad value, a missing config file or directory, or a
            user config that shadows a built-in one (Hydra's message, without its chained causes).
    """
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        config_dirs = _check_config_dirs(list(config_dirs))
        for_hydra, for_mappings = _prepare_overrides(overrides, config_dirs)
        cfg = _compose(name, for_hydra, config_dirs)
        _apply_mapping_overrides(cfg, for_mappings)
        OmegaConf.resolve(cfg)
    except (HydraException, OmegaConfBaseException) as err:
        # Hydra's messages name the key and the options; its chained causes add only noise.
        raise ConfigError(str(err).strip()) from None
    return cfg


def config_or_overrides(name: str, config: DictConfig | None, overrides: Sequence[str]) -> DictConfig:
    """What a Python entry point (``mmf_rl.train``, ``mmf_rl.evaluate``) runs: ``config`` as given, or
    ``configs/<name>.yaml`` composed with ``overrides``.

    Args:
        name (str): the config composed when ``config`` is ``None`` (``"train"``, ``"eval"``, ...).
        config (DictConfig | None): a composed config, used as given.
        overrides (Sequence[str]): Hydra overrides; only without ``config``.

    Returns:
        The config to run.

    Raises:
        ValueError: both ``config`` and ``overrides`` given.
    """
    if config is None:
        return compose_config(name, list(overrides))
    if overrides:
        raise ValueError(
            f"pass a composed config or overrides, not both: edit the config, or compose it with every "
            f"override (compose_config({name!r}, overrides))"
        )
    return config


@dataclass
class ConfigCommand:
    """A parsed ``mmf-rl <command> [--config-dir DIR] [--cfg] [overrides]`` command line.

    Args:
        overrides (list[str]): the Hydra overrides, in command-line order.
        config_dirs (list[Path]): the ``--config-dir`` directories.
        print_config (bool): ``--cfg`` was given: print the composed config and exit.
    """

    overrides: list[str]
    config_dirs: list[Path]
    print_config: bool

    def compose(self, name: str) -> DictConfig:
        """The config ``name`` with this command line's overrides (:func:`compose_config`).

        Args:
            name (str): the config's name.

        Returns:
            The composed config.
        """
        return compose_config(name, self.overrides, self.config_dirs)


def _settings_help(name: str, config_dirs: list[Path]) -> str:
    """The config's groups with their options (defaults marked), and its own top-level keys."""
    path = config_dir() / f"{name}.yaml"
    own = OmegaConf.load(path)
    defaults = {}
    for entry in own.get("defaults", []):
        if isinstance(entry, DictConfig):
            defaults.update({str(k): v for k, v in entry.items()})
    lines = []
    groups = {g: o for g, o in config_groups(config_dirs).items() if g in defaults}
    if groups:
        lines += ["config groups (GROUP=OPTION, or GROUP=/path/to/file.yaml; * marks the default):"]
        for group, options in groups.items():
            marked = [f"{o}*" if o == defaults[group] else o for o in options]
            lines.append(f"  {group:<11} {', '.join(marked)}")
        lines.append("")
    plain = OmegaConf.to_container(own, resolve=False)
    scalars = {k: v for k, v in plain.items() if k != "defaults" and not isinstance(v, (dict, list))}
    if scalars:
        lines.append(f"settings (KEY=VALUE; defaults from {path}):")
        lines += [f"  {OmegaConf.to_yaml({k: v}).strip().replace(': ', '=', 1)}" for k, v in scalars.items()]
        lines.append("")
    lines.append(
        "overrides: KEY=VALUE sets a key, GROUP=OPTION picks a config, +KEY=VALUE adds a key (Hydra syntax)."
    )
    if "data" in groups:
        lines += [
            f"A whole mapping for {', '.join(REPLACED_MAPPINGS)} replaces the config's; a dotted key",
            "then edits one entry (whether or not the entry gives that key yet):",
            "  data.modalities='{cam: observation.images.top, joints: observation.state}' "
            "data.modalities.cam.encoder=conv_gru",
        ]
    return "\n".join(lines)


def add_config_dir_flag(parser: argparse.ArgumentParser) -> None:
    """Add ``--config-dir DIR``, repeatable: the user's own config directories, as every command
    composing a Hydra config takes them.

    Args:
        parser (argparse.ArgumentParser): the command's parser, given the flag in place.
    """
    parser.add_argument(
        "--config-dir",
        action="append",
        type=Path,
        default=[],
        metavar="DIR",
        help="a directory of your own configs (<group>/<name>.yaml, e.g. data/mine.yaml -> data=mine); "
        "repeatable",
    )


def parse_config_command(argv: list[str], name: str, description: str, examples: list[str]) -> ConfigCommand:
    """Parse a Hydra-config command's arguments; ``--help`` prints usage, the config groups and their
    options, and ``examples`` (then exits, as argparse does).

    Args:
        argv (list[str]): the arguments after the command's name.
        name (str): the config the command composes (its ``--help`` lists that config's groups).
        description (str): the help's description.
        examples (list[str]): example command lines, listed at the end of the help.

    Returns:
        The parsed command line.
    """
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config-dir", action="append", type=Path, default=[])
    known, _ = pre.parse_known_args(argv)
    try:
        settings = _settings_help(name, _check_config_dirs(known.config_dir))
    except ConfigError as err:
        settings = f"(config groups unavailable: {err})\n"
    epilog = "\n".join(
        [
            settings,
            "",
            "examples:",
            *(f"  {example}" for example in examples),
        ]
    )
    parser = argparse.ArgumentParser(
        prog=f"mmf-rl {name}",
        description=description,
        epilog=epilog,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_config_dir_flag(parser)
    parser.add_argument(
        "--cfg", action="store_true", help="print the composed config (YAML) and exit without running"
    )
    parser.add_argument(
        "overrides", nargs="*", metavar="OVERRIDE", help="KEY=VALUE or GROUP=OPTION (Hydra syntax)"
    )
    args = parser.parse_intermixed_args(argv)
    return ConfigCommand(overrides=args.overrides, config_dirs=args.config_dir, print_config=args.cfg)


def run_config_command(
    argv: list[str],
    name: str,
    description: str,
    examples: list[str],
    run: Callable[[DictConfig], T],
    errors: tuple[type[Exception], ...],
    show: Callable[[T], None] = lambda result: None,
) -> int:
    """``mmf-rl <name> [--config-dir DIR] [--cfg] [overrides]``, the skeleton every Hydra-config command
    shares: parse the arguments (:func:`parse_config_command`), compose ``configs/<name>.yaml`` with the
    overrides, then print it (``--cfg``) or ``run`` it and ``show`` the result on stdout.

    Args:
        argv (list[str]): the arguments after the command's name.
        name (str): the config the command composes (``configs/<name>.yaml``).
        description (str): the help's description.
        examples (list[str]): example command lines, listed at the end of the help.
        run (Callable[[DictConfig], T]): what the command does with the composed config.
        errors (tuple[type[Exception], ...]): the expected failures, reported in one line.
        show (Callable[[T], None], optional): prints ``run``'s result. Defaults to printing nothing.

    Returns:
        The exit code: 0, or 1 for an expected failure, one of ``errors`` (one line on stderr:
        :func:`report_command_error`).
    """
    command = parse_config_command(argv, name, description, examples)
    try:
        cfg = command.compose(name)
        if command.print_config:
            print(OmegaConf.to_yaml(cfg), end="")
            return 0
        result = run(cfg)
    except errors as err:
        return report_command_error(f"mmf-rl {name}", err)
    show(result)
    return 0


def report_command_error(command: str, error: Exception) -> int:
    """A command's expected failure (bad config, missing file, bad data) as one line on stderr, exit
    code 1; with ``MMF_RL_DEBUG`` set the exception propagates with its traceback. Call it from the
    ``except`` block that caught ``error``. A ``KeyError`` shows its message without the quotes
    ``str(KeyError)`` adds.

    Args:
        command (str): the command's name, the message's prefix.
        error (Exception): the caught exception.

    Returns:
        ``1``, the command's exit code.

    Raises:
        Exception: ``error`` itself, when ``MMF_RL_DEBUG`` is set.
    """
    if os.environ.get("MMF_RL_DEBUG"):
        raise error
    message = error.args[0] if isinstance(error, KeyError) and error.args else error
    print(f"{command}: error: {message}", file=sys.stderr)
    return 1


def to_container(cfg: DictConfig) -> dict:
    """A config as plain, resolved Python containers.

    Args:
        cfg (DictConfig): the config.

    Returns:
        A dict of dicts, lists and scalars, interpolations resolved.
    """
    return OmegaConf.to_container(cfg, resolve=True)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to a temp file beside ``path``, then rename it over ``path``: a reader sees the
    old file or the new one, never a half-written one.

    Args:
        path (Path): the file to write (its parent directories are created).
        text (str): its new content.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def save_config(cfg: DictConfig | dict, path: Path, header: str = "") -> None:
    """Write a config as YAML atomically (temp file + rename), after ``header``.

    Args:
        cfg (DictConfig | dict): the config.
        path (Path): the YAML file to write.
        header (str, optional): text written first (comment lines, each starting with ``#``).
    """
    config = cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)
    write_text_atomic(path, header + OmegaConf.to_yaml(config))


def load_config(path: Path) -> DictConfig:
    """Read a YAML config (one :func:`save_config` wrote).

    Args:
        path (Path): the YAML file.

    Returns:
        The config, interpolations unresolved.
    """
    return OmegaConf.load(path)


def config_changes(saved: dict, current: dict, ignore=frozenset()) -> tuple[dict, dict]:
    """How the config ``current`` differs from a run's ``saved`` one (both plain containers), by dotted
    key: ``(added, changed)``, the settings ``saved`` lacks (a newer mmf-rl added them) with their
    current value, and the settings whose value differs as ``(saved, current)``. Keys in ``ignore``
    are left out.

    Args:
        saved (dict): the run's saved config, plain containers.
        current (dict): the config now, plain containers.
        ignore (Collection[str], optional): dotted keys left out of both results.

    Returns:
        ``(added, changed)``: ``{key: current value}`` and ``{key: (saved value, current value)}``,
        sorted by key.
    """

    def flat(d: dict, prefix: str = ""):
        for k, v in d.items():
            if isinstance(v, dict):
                yield from flat(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    a, b = dict(flat(saved)), dict(flat(current))
    added = {k: b[k] for k in sorted(set(b) - set(a) - set(ignore))}
    changed = {
        k: (a.get(k), b.get(k))
        for k in sorted(set(a) | set(b))
        if k not in added and k not in ignore and a.get(k) != b.get(k)
    }
    return added, changed
