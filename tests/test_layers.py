"""The package's import graph only points down its layers (README, "Layout"), and a command's
module is the CLI's alone; the benchmarks sit on top: they import the package, which never imports them
(nor the tests), and their packages never import a script."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "mmf_rl"
BENCHMARKS = REPO / "benchmarks"

# Bottom to top; a module may import its own layer's modules or lower ones, never a higher layer.
LAYERS: list[set[str]] = [
    {"keys", "configuration", "checkpoint", "devices", "temp_dirs", "shards", "log"},
    {"envs"},
    {"datasets"},
    {"record"},
    {"objectives"},
    {"models"},
    {"trainers", "eval"},
    {"rl"},
    {"cli", "demo", "bench", "compare"},
]
RANK = {name: rank for rank, layer in enumerate(LAYERS) for name in layer}


def imported_modules(path: Path) -> set[str]:
    """The modules ``path`` imports by absolute name, at its top or inside a function; ``from a import
    b`` gives ``a`` and ``a.b`` (``b`` may be a module)."""
    return set(_imported_modules(path.read_text(), str(path)))


@functools.cache
def _imported_modules(source: str, filename: str) -> frozenset[str]:
    """``imported_modules`` of a file's text (each text parsed once: the tests below read the package's
    files again and again)."""
    modules = set()
    for node in ast.walk(ast.parse(source, filename=filename)):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            modules |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            modules |= {a.name for a in node.names}
    return frozenset(modules)


def import_edges(package: Path) -> set[tuple[str, str, str]]:
    """``(importing file, its top-level unit, imported top-level unit)`` for every ``mmf_rl`` import."""
    edges = set()
    for path in sorted(package.rglob("*.py")):
        unit = path.relative_to(package).parts[0].removesuffix(".py")
        for name in imported_modules(path):
            parts = name.split(".")
            if parts[0] == "mmf_rl" and len(parts) > 1 and parts[1] != unit:
                edges.add((str(path.relative_to(package.parent)), unit, parts[1]))
    return edges


def upward_imports(package: Path, benchmarks: Path) -> list[str]:
    """Imports of the benchmarks or the tests by ``package``, and of a benchmark script (a module at the
    top of ``benchmarks``) by a benchmark package: each points up, from a layer its importer is under."""
    scripts = {f"benchmarks.{path.stem}" for path in benchmarks.glob("*.py") if path.stem != "__init__"}
    problems = []
    for path in sorted(package.rglob("*.py")):
        above = outermost(m for m in imported_modules(path) if m.split(".")[0] in ("benchmarks", "tests"))
        problems += [f"{path.relative_to(package.parent)} imports {m}" for m in above]
    for path in sorted(benchmarks.glob("*/**/*.py")):
        above = outermost(m for m in imported_modules(path) if ".".join(m.split(".")[:2]) in scripts)
        problems += [f"{path.relative_to(benchmarks.parent)} imports the script {m}" for m in above]
    return problems


def outermost(modules) -> list[str]:
    """``modules`` without those inside another of them (``a.b.c`` when ``a.b`` is there), sorted."""
    modules = set(modules)
    return sorted(m for m in modules if not any(m.startswith(f"{o}.") for o in modules))


def layer_violations(package: Path) -> list[str]:
    problems = []
    edges = import_edges(package)
    units = {unit for _, unit, _ in edges} | {dst for _, _, dst in edges}
    unknown = sorted(u for u in units if u not in RANK and u != "__init__")
    problems += [f"mmf_rl.{u} has no layer: add it to tests/test_layers.py LAYERS" for u in unknown]
    pairs = {(src, dst) for _, src, dst in edges}
    for path, src, dst in sorted(edges):
        if src in RANK and dst in RANK and RANK[dst] > RANK[src]:
            problems.append(f"{path}: {src} imports {dst}, a higher layer")
        elif src in RANK and RANK.get(dst) == RANK[src] and (dst, src) in pairs:
            problems.append(f"{path}: {src} imports {dst}, which imports {src} back")
    return problems


def test_imports_only_point_down():
    assert layer_violations(PACKAGE) == []


def test_the_package_never_imports_the_benchmarks_and_their_packages_never_import_a_script():
    assert upward_imports(PACKAGE, BENCHMARKS) == []


def test_an_import_of_the_benchmarks_lazy_or_not_or_of_a_script_is_reported(tmp_path):
    files = {
        "mmf_rl/rl/bc.py": "def train():\n    from benchmarks.push.gmm_head import GMMPolicy\n",
        "mmf_rl/datasets/windows.py": "import tests.conftest\n",
        "benchmarks/bc_push.py": "from benchmarks.push.closed_loop import OUTAGES\n",
        "benchmarks/push/closed_loop.py": "import mmf_rl.rl\nfrom benchmarks.bc_push import main\n",
        "benchmarks/push/dagger.py": "from benchmarks import bc_push, push\n",
    }
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert upward_imports(tmp_path / "mmf_rl", tmp_path / "benchmarks") == [
        "mmf_rl/datasets/windows.py imports tests.conftest",
        "mmf_rl/rl/bc.py imports benchmarks.push.gmm_head",
        "benchmarks/push/closed_loop.py imports the script benchmarks.bc_push",
        "benchmarks/push/dagger.py imports the script benchmarks.bc_push",
    ]


@pytest.mark.parametrize(
    "source, expected",
    [
        ("from mmf_rl.models import build_model\n", "datasets imports models, a higher layer"),
        (
            "def f():\n    from mmf_rl.rl.transforms import HistoryWindow\n",
            "datasets imports rl, a higher layer",
        ),
        ("import mmf_rl.trainers.trainer\n", "datasets imports trainers, a higher layer"),
        ("from mmf_rl import eval\n", "datasets imports eval, a higher layer"),
    ],
)
def test_an_upward_import_is_reported(tmp_path, source, expected):
    package = tmp_path / "mmf_rl"
    (package / "datasets").mkdir(parents=True)
    (package / "datasets" / "windows.py").write_text(source)
    assert layer_violations(package) == [f"mmf_rl/datasets/windows.py: {expected}"]


def test_a_loop_within_a_layer_is_reported(tmp_path):
    package = tmp_path / "mmf_rl"
    for unit, other in (("trainers", "eval"), ("eval", "trainers")):
        (package / unit).mkdir(parents=True)
        (package / unit / "run.py").write_text(f"from mmf_rl.{other}.run import main\n")
    assert layer_violations(package) == [
        "mmf_rl/eval/run.py: eval imports trainers, which imports eval back",
        "mmf_rl/trainers/run.py: trainers imports eval, which imports trainers back",
    ]


# --- a command's module (`mmf_rl.eval.eval_command`, `mmf_rl.compare.command`) is the CLI's -------------


COMMAND_MODULES = sorted(
    ".".join(("mmf_rl", *path.relative_to(PACKAGE).with_suffix("").parts))
    for path in PACKAGE.rglob("*.py")
    if re.fullmatch(r"(\w+_)?command", path.stem)
)
CODE_DIRS = ("mmf_rl", "benchmarks", "examples", "scripts", "tests")


def command_imports(repo: Path) -> list[str]:
    """Imports of a command's module from outside its own unit of ``mmf_rl``. The CLI reaches the
    commands by name; other code goes through ``mmf_rl.train``/``mmf_rl.evaluate`` or the module that
    holds the command's logic, so that a command's module holds only its command line."""
    problems = []
    for path in sorted(p for top in CODE_DIRS for p in (repo / top).rglob("*.py")):
        relative = path.relative_to(repo)
        modules = {
            m
            for name in imported_modules(path)
            for m in COMMAND_MODULES
            if name == m or name.startswith(f"{m}.")
        }
        problems += [
            f"{relative}: imports {m}"
            for m in sorted(modules)
            if relative.parts[:2] != ("mmf_rl", m.split(".")[1])
        ]
    return problems


def test_no_command_module_is_imported_from_another_package():
    assert command_imports(REPO) == []


@pytest.mark.parametrize(
    "path, source, expected",
    [
        (
            "mmf_rl/demo.py",
            "from mmf_rl.trainers.train_command import train\n",
            "mmf_rl.trainers.train_command",
        ),
        (
            "mmf_rl/rl/experiment.py",
            "def f():\n    from mmf_rl.eval import eval_command\n",
            "mmf_rl.eval.eval_command",
        ),
        ("benchmarks/x.py", "import mmf_rl.compare.command\n", "mmf_rl.compare.command"),
        (
            "tests/test_x.py",
            "from mmf_rl.eval.calibrate_command import main\n",
            "mmf_rl.eval.calibrate_command",
        ),
    ],
)
def test_a_command_module_imported_from_elsewhere_is_reported(tmp_path, path, source, expected):
    (tmp_path / path).parent.mkdir(parents=True)
    (tmp_path / path).write_text(source)
    (tmp_path / "mmf_rl" / "eval").mkdir(parents=True, exist_ok=True)
    (tmp_path / "mmf_rl" / "eval" / "calibration.py").write_text("from mmf_rl.eval.eval_command import x\n")
    assert command_imports(tmp_path) == [f"{path}: imports {expected}"]
