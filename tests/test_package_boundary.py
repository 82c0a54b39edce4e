"""The package holds the library; the experiments live beside it, in ``benchmarks/``: every module of
``mmf_rl`` is reached from the package's own entry points (the CLI, the package ``__init__``s) through
library modules, so none is there only for a benchmark."""

from __future__ import annotations

import ast
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "mmf_rl"
# The CLI names its commands' modules ("mmf_rl.eval.eval_command", "mmf_rl.cli:record") and
# `mmf_rl.envs` its lazy exports' as strings for importlib: a string naming a module imports it too.
MODULE_STRING = re.compile(r"mmf_rl(\.\w+)+(:\w+)?")


def module_names(package: Path) -> dict[str, Path]:
    """``{dotted name: path}`` of every module of ``package`` (a package is its ``__init__``)."""
    names = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(package.parent).with_suffix("").parts
        names[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return names


def imported_names(path: Path) -> set[str]:
    """Every dotted name ``path`` imports, at its top or inside a function (a lazy import is still a
    use); ``from a import b`` gives ``a`` and ``a.b`` (``b`` may be a submodule)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and MODULE_STRING.fullmatch(node.value)
        ):
            names.add(node.value.partition(":")[0])
    return names


def unreachable_modules(package: Path) -> list[str]:
    """The modules of ``package`` that no chain of imports reaches from its entry points: its CLI
    (``<package>.cli``) and its package ``__init__``s, what a user imports or runs."""
    modules = module_names(package)
    edges = {}
    for name, path in modules.items():
        # Importing a.b.c runs a, a.b and a.b.c.
        dotted = [n.split(".") for n in imported_names(path)]
        edges[name] = {".".join(p[:i]) for p in dotted for i in range(1, len(p) + 1)} & modules.keys()
    entry_points = {f"{package.name}.cli"} | {n for n, p in modules.items() if p.name == "__init__.py"}
    reached, frontier = set(), entry_points & modules.keys()
    while frontier:
        reached |= frontier
        frontier = set().union(*(edges[n] for n in frontier)) - reached
    return sorted(modules.keys() - reached)


def test_every_module_of_the_package_is_reached_from_its_entry_points():
    unreachable = unreachable_modules(PACKAGE)
    assert unreachable == [], (
        f"{unreachable}: no entry point of mmf_rl (the CLI, a package __init__) reaches these modules "
        "through library code; a module only a benchmark uses belongs in benchmarks/ (e.g. benchmarks/push/)"
    )


def fake_tree(package: Path, files: dict[str, str]) -> Path:
    """``package`` with ``files`` (paths from its parent: the repository) written beside it."""
    for name, text in files.items():
        path = package.parent / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return package


def test_a_module_only_a_benchmark_imports_is_reported_with_what_only_it_imports(tmp_path):
    package = fake_tree(
        tmp_path / "mmf_rl",
        {
            "mmf_rl/__init__.py": "",
            "mmf_rl/cli.py": "from mmf_rl.rl import transforms\n",
            "mmf_rl/rl/__init__.py": '"""See mmf_rl.rl.experiment, which benchmarks import."""\n',
            "mmf_rl/rl/transforms.py": "",
            "mmf_rl/rl/experiment.py": "from mmf_rl.rl.closed_loop import play\n",
            "mmf_rl/rl/closed_loop.py": "import mmf_rl.rl.transforms\n",
            "benchmarks/mpc_push.py": "from mmf_rl.rl.experiment import run\n",
        },
    )
    assert unreachable_modules(package) == ["mmf_rl.rl.closed_loop", "mmf_rl.rl.experiment"]


def test_lazy_imports_submodules_and_the_clis_command_strings_reach_a_module(tmp_path):
    package = fake_tree(
        tmp_path / "mmf_rl",
        {
            "mmf_rl/__init__.py": "",
            "mmf_rl/cli.py": 'COMMANDS = {"a": "mmf_rl.trainers.train_command", "b": "mmf_rl.cli:record"}\n',
            "mmf_rl/trainers/__init__.py": "",
            "mmf_rl/trainers/train_command.py": "def main():\n    from mmf_rl.eval import report\n",
            "mmf_rl/eval/__init__.py": "",
            "mmf_rl/eval/report.py": "",
        },
    )
    assert unreachable_modules(package) == []
    (package / "cli.py").write_text("COMMANDS = {}\n")
    assert unreachable_modules(package) == ["mmf_rl.eval.report", "mmf_rl.trainers.train_command"]
