"""Count the test suite's tests and checks, to show that a change to the suite keeps its checks.

Prints two kinds of numbers:

* tests: the test items ``pytest --collect-only -q`` collects from ``tests/`` (a parametrized test counts
  once per parameter set), overall and with ``-m "not slow"`` (the fast tier, ``make test-fast``);
* checks, counted statically in every ``*.py`` file under ``tests/`` (each occurrence in the source
  once, however often it runs):
  - ``assert``: ``assert`` statements;
  - ``pytest.raises``: calls of ``pytest.raises`` (as a context manager or called directly);
  - ``pytest.approx``: calls of ``pytest.approx``;
  - ``assert_*`` calls: calls of a function or method whose name starts with ``assert_`` (e.g.
    ``torch.testing.assert_close``, ``np.testing.assert_allclose``, the suite's own helpers);
  - total: the sum of the four.

Usage: ``python scripts/count_checks.py [--no-collect]`` from the repository's root (``--no-collect``
skips pytest's collection, which imports every test module).
"""

from __future__ import annotations

import argparse
import ast
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

TESTS = Path("tests")


def called_name(call: ast.Call) -> str | None:
    """The name of what ``call`` calls: ``f`` for ``f(...)``, ``attr`` for ``x.y.attr(...)``."""
    func = call.func
    if isinstance(func, ast.Name):
        return func.id
    if isinstance(func, ast.Attribute):
        return func.attr
    return None


def is_pytest_call(call: ast.Call, name: str) -> bool:
    """Whether ``call`` is ``pytest.<name>(...)``."""
    func = call.func
    return (
        isinstance(func, ast.Attribute)
        and func.attr == name
        and isinstance(func.value, ast.Name)
        and func.value.id == "pytest"
    )


def count_checks(paths: list[Path]) -> Counter:
    """The checks in the source files ``paths``, by kind (see the module's docstring)."""
    counts: Counter = Counter()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Assert):
                counts["assert"] += 1
            elif isinstance(node, ast.Call):
                if is_pytest_call(node, "raises"):
                    counts["pytest.raises"] += 1
                elif is_pytest_call(node, "approx"):
                    counts["pytest.approx"] += 1
                elif (called_name(node) or "").startswith("assert_"):
                    counts["assert_* calls"] += 1
    counts["total"] = sum(counts.values())
    return counts


def collected_tests(*marker: str) -> int:
    """How many tests ``pytest --collect-only -q tests`` collects (with ``-m MARKER`` if given)."""
    args = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    if marker:
        args += ["-m", *marker]
    out = subprocess.run([*args, str(TESTS)], capture_output=True, text=True, check=False).stdout
    # The last line reads "N tests collected" or "N/M tests collected (K deselected)".
    found = re.search(r"^(\d+)(?:/\d+)? tests? collected", out, re.MULTILINE)
    if found is None:
        raise RuntimeError(f"pytest's collection gave no count:\n{out[-2000:]}")
    return int(found.group(1))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-collect", action="store_true", help="count the checks only")
    args = parser.parse_args(argv)
    files = sorted(TESTS.rglob("*.py"))
    if not args.no_collect:
        print(f"tests collected: {collected_tests()}")
        print(f"tests collected without slow: {collected_tests('not slow')}")
    print(f"test files: {len(files)}")
    for kind, n in sorted(count_checks(files).items()):
        print(f"{kind}: {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
