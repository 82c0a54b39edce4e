"""The documentation: the site (mkdocs.yml, docs/) builds with --strict, every benchmark has a page whose
first table names the commit it came from, and the README's and the site's Python blocks run.

A ```python block runs unless the line before it says ``<!-- not executed: REASON -->``; one preceded by
``<!-- test: trained runs -->`` runs in a directory holding tiny trained runs under the paths the pages
use (``runs/push``, ``runs/demo``, ``runs/mine``: a push forecaster; ``runs/world_model``: a push world
model), with ``SHRINK``'s substitutions making its budgets test-sized. The blocks of one page run in
order in one namespace, as a reader runs them.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
NOT_EXECUTED = re.compile(r"<!-- not executed: (?P<reason>\S.*?) -->")
TRAINED_RUNS = "<!-- test: trained runs -->"
# What makes a page's example test-sized: the tiny runs are recorded at 32 px, and a rollout, a
# vectorised env or a training needs only to run, not to be long.
SHRINK = [
    ("image_size=64", "image_size=32"),
    ("env.rollout(50", "env.rollout(3"),
    ("SerialEnv(4,", "SerialEnv(2,"),
    ("total_steps=3000", "total_steps=2"),
    ("batch_size=128", "batch_size=8"),
]


def mkdocs_build(root: Path, site: Path) -> subprocess.CompletedProcess:
    """``mkdocs build --strict`` of ``root/mkdocs.yml`` into ``site``, run from ``root`` (the snippets'
    and mkdocstrings' paths are relative to it)."""
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", "mkdocs.yml", "-d", str(site)],
        cwd=root,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )


@pytest.mark.slow
def test_the_site_builds_strict(tmp_path):
    build = mkdocs_build(REPO, tmp_path / "site")
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-4000:]
    api = (tmp_path / "site" / "api" / "rl" / "index.html").read_text()
    assert 'id="mmf_rl.rl.ForecastTransform"' in api, "the API reference rendered no docstrings"
    extending = (tmp_path / "site" / "extending" / "index.html").read_text()
    assert "register_fusion" in extending, "docs/extending.md no longer includes the README's examples"


def site_copy(tmp_path: Path) -> Path:
    """The site's sources copied into ``tmp_path``, the API pages without their ``:::`` blocks (so that a
    build of the copy is quick and fails only for what a test puts in)."""
    root = tmp_path / "copy"
    shutil.copytree(DOCS, root / "docs")
    for name in ("mkdocs.yml", "README.md"):
        shutil.copy(REPO / name, root / name)
    for page in (root / "docs" / "api").glob("*.md"):
        page.write_text(re.sub(r"^::: .*(\n    .*)*$", "", page.read_text(), flags=re.M))
    return root


@pytest.mark.slow
def test_the_strict_build_fails_on_a_broken_link_or_anchor_a_page_off_the_nav_or_a_bad_docstring(tmp_path):
    """One build of a copy holding four breakages: strict mode reports every warning before it aborts."""
    root = site_copy(tmp_path)
    page = root / "docs" / "getting-started.md"
    broken = "\nSee [this](no_such_page.md) and [that](models.md#no-such-section).\n"
    page.write_text(page.read_text() + broken)
    (root / "docs" / "orphan.md").write_text("# Orphan\n")
    (root / "docs_broken.py").write_text(
        'def f(a):\n    """Do.\n\n    Args:\n        a the first, without its colon\n    """\n'
    )
    (root / "docs" / "api" / "keys.md").write_text("# keys\n\n::: docs_broken.f\n")
    build = mkdocs_build(root, tmp_path / "site")
    assert build.returncode != 0, "the strict build passed"
    output = build.stdout + build.stderr
    for breakage, expected in [
        ("a broken link", "contains a link 'no_such_page.md'"),
        ("a broken anchor", "does not contain an anchor '#no-such-section'"),
        ("a page missing from the nav", 'not included in the "nav" configuration:\n  - orphan.md'),
        ("a docstring that does not render", "Failed to get 'name: description' pair"),
    ]:
        assert expected in output, f"the build did not report {breakage}:\n{output[-3000:]}"


@pytest.mark.slow
def test_the_strict_build_fails_on_an_api_page_of_a_module_that_does_not_exist(tmp_path):
    root = site_copy(tmp_path)
    (root / "docs" / "api" / "keys.md").write_text("# keys\n\n::: mmf_rl.no_such_module\n")
    build = mkdocs_build(root, tmp_path / "site")
    assert build.returncode != 0, "the strict build passed"
    assert "Could not collect 'mmf_rl.no_such_module'" in build.stdout + build.stderr


def benchmark_scripts() -> list[str]:
    """The benchmarks: the scripts under benchmarks/ (a module without a ``__main__`` guard is a helper)."""
    return sorted(
        path.stem
        for path in (REPO / "benchmarks").rglob("*.py")
        if 'if __name__ == "__main__":' in path.read_text()
    )


@pytest.mark.slow
def test_every_benchmark_has_a_page_in_the_nav_whose_first_table_names_its_commit():
    scripts = benchmark_scripts()
    assert len(scripts) >= 10, scripts
    nav = (REPO / "mkdocs.yml").read_text()
    git = (REPO / ".git").exists() and shutil.which("git") is not None
    for script in scripts:
        page = DOCS / "benchmarks" / f"{script}.md"
        assert page.is_file(), f"benchmarks/{script}.py has no page docs/benchmarks/{script}.md"
        assert f"benchmarks/{script}.md" in nav, f"docs/benchmarks/{script}.md is not in mkdocs.yml's nav"
        text = page.read_text()
        sections = [line for line in text.splitlines() if line.startswith("## ")]
        assert sections[:2] == ["## The command", "## Current result"], (script, sections)
        assert "## How" in text, f"{page.name} does not say how its defaults were chosen"
        # The first table is the current result: the lines after it name the commit it came from.
        first_table = text.index("\n|")
        after = text[first_table:].split("\n\n", 1)[1].split("\n\n", 1)[0]
        commits = re.findall(r"(?:Recorded in|Measured at) `([0-9a-f]{7,40})`", after)
        assert commits, f"{page.name}: no 'Recorded in `COMMIT`' under its first table"
        if git:
            for commit in commits:
                found = subprocess.run(
                    ["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=REPO, capture_output=True
                )
                assert found.returncode == 0, f"{page.name} names {commit}, which is not a commit"


def test_the_readme_is_a_users_page_of_at_most_300_lines_without_dates():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 300, "README.md: at most 300 lines; move the detail to docs/"
    dated = re.findall(r"\b20\d\d-\d\d-\d\d\b", text)
    assert not dated, f"README.md names dates {dated}: history belongs in the notes, not the user's page"


def python_blocks(page: Path) -> list[tuple[str, str | None]]:
    """The page's ```python blocks in order, each as (code, marker): marker None, ``TRAINED_RUNS``, or
    ``"skip"`` for a block marked not executed (its reason is required)."""
    lines = page.read_text().splitlines()
    blocks = []
    for i, line in enumerate(lines):
        if line.strip() != "```python":
            continue
        end = lines.index("```", i + 1)
        before = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        if before.startswith("<!-- not executed"):
            assert NOT_EXECUTED.fullmatch(before), f"{page.name}: a block not executed must say why: {before}"
            marker = "skip"
        else:
            marker = TRAINED_RUNS if before == TRAINED_RUNS else None
        blocks.append(("\n".join(lines[i + 1 : end]) + "\n", marker))
    return blocks


PAGES = [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]
PAGES_WITH_CODE = [page for page in PAGES if python_blocks(page)]


def test_the_pages_hold_python_examples():
    names = {page.relative_to(REPO).as_posix() for page in PAGES_WITH_CODE}
    assert {"README.md", "docs/getting-started.md", "docs/torchrl.md"} <= names, names
    skipped = [page.name for page in PAGES for _, marker in python_blocks(page) if marker == "skip"]
    assert len(skipped) <= 2, f"illustrative blocks should be rare: {skipped}"


def run_blocks(page: Path, blocks: list[tuple[str, str | None]]) -> None:
    """Run the blocks in order in one module of their own (a dataclass needs its module in sys.modules)."""
    module = types.ModuleType("docs_example_" + re.sub(r"\W", "_", page.stem))
    sys.modules[module.__name__] = module
    try:
        for index, (code, marker) in enumerate(blocks):
            if marker == "skip":
                continue
            for old, new in SHRINK:
                code = code.replace(old, new)
            exec(compile(code, f"{page.name} (python block {index + 1})", "exec"), module.__dict__)
    finally:
        del sys.modules[module.__name__]


@pytest.fixture
def restored_registries():
    """A page's examples may register a fusion, a model or a loss term; they are removed afterwards."""
    from mmf_rl.models import MODELS
    from mmf_rl.models.fusion import FUSIONS
    from mmf_rl.objectives import LOSS_TERMS

    registries = [MODELS, FUSIONS, LOSS_TERMS]
    saved = [dict(registry) for registry in registries]
    yield
    for registry, before in zip(registries, saved, strict=True):
        registry.clear()
        registry.update(before)


@pytest.fixture(scope="session")
def docs_runs(push_forecaster_run, push_world_model_run, tmp_path_factory) -> Path:
    """A directory holding the runs the pages' examples name: a copy of the session's tiny push
    forecaster, which the examples may evaluate into (``runs/push``, ``runs/demo``, ``runs/mine``), and
    the session's tiny world model (``runs/world_model``)."""
    root = tmp_path_factory.mktemp("docs_runs")
    run = Path(shutil.copytree(push_forecaster_run, root / "runs" / "push"))
    for name in ("demo", "mine"):
        (root / "runs" / name).symlink_to(run, target_is_directory=True)
    (root / "runs" / "world_model").symlink_to(push_world_model_run, target_is_directory=True)
    return root


# A page whose blocks read trained runs waits for the session's recording and runs: the slow tier.
@pytest.mark.parametrize(
    "page",
    [
        pytest.param(page, marks=pytest.mark.slow)
        if any(marker == TRAINED_RUNS for _, marker in python_blocks(page))
        else page
        for page in PAGES_WITH_CODE
    ],
    ids=lambda page: page.relative_to(REPO).as_posix(),
)
def test_a_pages_python_blocks_run(page, request, restored_registries, tmp_path, monkeypatch):
    blocks = python_blocks(page)
    if any(marker == TRAINED_RUNS for _, marker in blocks):
        monkeypatch.chdir(request.getfixturevalue("docs_runs"))
    else:
        monkeypatch.chdir(tmp_path)
    run_blocks(page, blocks)


def test_a_failing_block_fails_its_page(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("# p\n\n```python\nx = 1\n```\n\n```python\nassert x == 2, 'the page is wrong'\n```\n")
    with pytest.raises(AssertionError, match="the page is wrong"):
        run_blocks(page, python_blocks(page))
    page.write_text("# p\n\n<!-- not executed -->\n```python\nx = 1\n```\n")
    with pytest.raises(AssertionError, match="must say why"):
        python_blocks(page)
