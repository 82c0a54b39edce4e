"""The public API's docstrings (what each package's ``__init__`` exports, and the public functions and
classes of ``mmf_rl.keys`` and ``mmf_rl.configuration``): each says what it takes (``Args:``, every
parameter with its type), what it returns, and what it raises on purpose; the main entry points carry
``Examples:``, run here as doctests, so they cannot drift from the code. The API reference of the docs
site is rendered from these docstrings."""

from __future__ import annotations

import ast
import doctest
import importlib
import inspect
import io
import re
import sys
import textwrap

import pytest
import torch

EXPORTING_MODULES = (
    "mmf_rl",
    "mmf_rl.keys",
    "mmf_rl.configuration",
    "mmf_rl.envs",
    "mmf_rl.datasets",
    "mmf_rl.objectives",
    "mmf_rl.models",
    "mmf_rl.models.forecaster",
    "mmf_rl.models.baselines",
    "mmf_rl.trainers",
    "mmf_rl.eval",
    "mmf_rl.rl",
    "mmf_rl.compare",
)

# The entry points a user starts from: each has an ``Examples:`` block that runs quickly on CPU.
MAIN_ENTRY_POINTS = (
    "mmf_rl.keys.ModalitySpec",
    "mmf_rl.models.ForecasterConfig",
    "mmf_rl.models.MultimodalForecaster",
    "mmf_rl.models.baselines.LateFusionLSTM",
    "mmf_rl.models.baselines.MVAE",
    "mmf_rl.models.baselines.MulT",
    "mmf_rl.models.baselines.ConstantVelocity",
    "mmf_rl.objectives.GaussianNLLLoss",
    "mmf_rl.objectives.ELBOLoss",
    "mmf_rl.objectives.MissingModalityLoss",
    "mmf_rl.objectives.DiverseSamplingLoss",
    "mmf_rl.objectives.CombinedLoss",
    "mmf_rl.objectives.ModalityDropout",
    "mmf_rl.envs.MultimodalPushTorchEnv",
    "mmf_rl.envs.ModalityDropout",
    "mmf_rl.datasets.DataConfig",
    "mmf_rl.datasets.WindowDataset",
    "mmf_rl.rl.ForecastTransform",
    "mmf_rl.rl.HistoryWindow",
    "mmf_rl.rl.WorldModel",
    "mmf_rl.rl.ForecasterWorldModelEnv",
)

ARGS_SECTIONS = ("Args", "Keyword Args")
SECTION = re.compile(r"^([A-Z][A-Za-z ]*):$")
# ``name (type): description``; ``*args``/``**kwargs`` may leave the type to what they are passed to.
ARG_ENTRY = re.compile(r"^(\*{0,2}\w+) \((.+?)\):(?:\s|$)|^(\*{1,2}\w+)():(?:\s|$)")


def exported(module) -> dict[str, object]:
    """The classes and functions ``module`` exports: its ``__all__``, else its public names defined in
    it (a module) or in ``mmf_rl`` (a package's ``__init__``)."""
    names = getattr(module, "__all__", None)
    if names is None:
        names = [name for name in vars(module) if not name.startswith("_")]
    is_package = hasattr(module, "__path__")
    found = {}
    for name in names:
        obj = getattr(module, name)
        if not (inspect.isclass(obj) or inspect.isfunction(obj)):
            continue
        home = getattr(obj, "__module__", "")
        if (
            hasattr(module, "__all__")
            or home == module.__name__
            or (is_package and home.startswith("mmf_rl"))
        ):
            found[f"{module.__name__}.{name}"] = obj
    return found


def public_objects() -> dict[str, object]:
    """Every exported class and function once, under the first name that exports it."""
    found, seen = {}, set()
    for module_name in EXPORTING_MODULES:
        for name, obj in exported(importlib.import_module(module_name)).items():
            if id(obj) not in seen:
                seen.add(id(obj))
                found[name] = obj
    return found


def sections(doc: str) -> dict[str, list[str]]:
    """A Google-style docstring's sections: title -> the section's lines (indented under the title)."""
    found, title = {}, None
    for line in doc.splitlines():
        match = SECTION.match(line)
        if match:
            title = match.group(1)
            found[title] = []
        elif title is not None:
            if line and not line.startswith(" "):
                title = None
            else:
                found[title].append(line)
    return found


def entries(lines: list[str]) -> list[str]:
    """The items of a section: its lines at the indentation of its first line."""
    lines = [line for line in lines if line.strip()]
    if not lines:
        return []
    indent = len(lines[0]) - len(lines[0].lstrip())
    return [line[indent:] for line in lines if len(line) - len(line.lstrip()) == indent]


def parameters(obj) -> list[str]:
    """The names a caller passes: the signature's (a class's without ``self``), ``*args``/``**kwargs``
    with their stars."""
    skip = 0
    if inspect.isclass(obj) and getattr(obj, "_is_protocol", False):
        return []  # a typing.Protocol is implemented, never constructed: its methods are the contract
    if inspect.isclass(obj):
        # The class's own __init__ (or __new__), not its metaclass's __call__ (torchrl's EnvBase has
        # one taking *args, **kwargs); none in Python (an exception class) or only a library mixin's
        # generic __new__ (huggingface's, under PretrainedModel): nothing to document.
        new = obj.__new__ if (getattr(obj.__new__, "__module__", None) or "").startswith("mmf_rl") else None
        obj = next((f for f in (obj.__init__, new) if inspect.isfunction(f)), None)
        if obj is None:
            return []
        skip = 1  # self, or the cls of __new__
    stars = {inspect.Parameter.VAR_POSITIONAL: "*", inspect.Parameter.VAR_KEYWORD: "**"}
    named = list(inspect.signature(obj).parameters.values())[skip:]
    return [stars.get(p.kind, "") + p.name for p in named]


def own_body(func) -> list[ast.AST]:
    """The AST nodes of ``func``'s own body (nested functions and classes left out)."""
    try:
        source = textwrap.dedent(inspect.getsource(inspect.unwrap(func)))
    except (OSError, TypeError):
        return []
    tree = ast.parse(source).body[0]
    nodes, stack = [], list(tree.body)
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)):
            continue
        nodes.append(node)
        stack.extend(ast.iter_child_nodes(node))
    return nodes


def raises_on_purpose(obj) -> bool:
    """``obj`` (a function, or a class's own ``__init__``/``__post_init__``) raises an exception it
    builds itself (not a bare re-raise)."""
    if getattr(obj, "_is_protocol", False):
        return False  # typing's __init__ of a Protocol refuses instantiation; the protocol raises nothing
    bodies = [obj] if inspect.isfunction(obj) else [vars(obj).get(n) for n in ("__init__", "__post_init__")]
    return any(
        isinstance(node, ast.Raise) and node.exc is not None
        for body in bodies
        if inspect.isfunction(body)
        for node in own_body(body)
    )


def docstring_problems(obj) -> list[str]:
    """What ``obj``'s docstring lacks; empty when it is complete."""
    doc = inspect.cleandoc(obj.__doc__ or "")  # its own: inspect.getdoc would fall back on a base's
    if not doc or not doc.splitlines()[0].strip():
        return ["no docstring with a one-line summary"]
    found = sections(doc)
    problems = []
    documented = {}
    for title in ARGS_SECTIONS:
        for entry in entries(found.get(title, [])):
            match = ARG_ENTRY.match(entry)
            if match is None:
                problems.append(f"{title}: {entry.split(':')[0]!r} is not `name (type): description`")
                continue
            documented[(match.group(1) or match.group(3)).lstrip("*")] = match.group(2) or match.group(4)
    params = parameters(obj)
    if params and not any(title in found for title in ARGS_SECTIONS):
        problems.append(f"takes {params} but has no Args: section")
    else:
        undocumented = [p for p in params if p.lstrip("*") not in documented]
        unknown = sorted(set(documented) - {p.lstrip("*") for p in params})
        if undocumented:
            problems.append(f"Args: does not document {undocumented}")
        if unknown:
            problems.append(f"Args: documents {unknown}, which are not parameters")
    if inspect.isfunction(obj):
        body = own_body(obj)
        if any(isinstance(n, (ast.Yield, ast.YieldFrom)) for n in body):
            if "Yields" not in found:
                problems.append("yields but has no Yields: section")
        elif any(isinstance(n, ast.Return) and n.value is not None for n in body) and "Returns" not in found:
            problems.append("returns a value but has no Returns: section")
    if raises_on_purpose(obj) and "Raises" not in found:
        problems.append("raises an exception of its own but has no Raises: section")
    return problems


def doctests(obj, name: str) -> list[doctest.DocTest]:
    """The doctests of ``obj``'s docstring and its methods', each with a namespace of its own."""
    return doctest.DocTestFinder().find(obj, name, module=sys.modules[obj.__module__], globs={})


def run_examples(obj, name: str) -> tuple[int, str]:
    """Run the ``>>>`` examples of ``obj``'s docstrings (its methods' included) in a namespace of their
    own: ``(examples run, failure report)``."""
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    report = io.StringIO()
    count = 0
    for test in doctests(obj, name):
        count += len(test.examples)
        runner.run(test, out=report.write)
    return count, report.getvalue()


PUBLIC = public_objects()


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_exported_docstring_documents_arguments_returns_and_raises(name):
    assert docstring_problems(PUBLIC[name]) == [], name


def test_main_entry_points_have_examples():
    for name in MAIN_ENTRY_POINTS:
        module, _, attr = name.rpartition(".")
        doc = inspect.cleandoc(getattr(importlib.import_module(module), attr).__doc__ or "")
        assert "Examples" in sections(doc) and ">>>" in doc, name


WITH_EXAMPLES = sorted(name for name, obj in PUBLIC.items() if any(t.examples for t in doctests(obj, name)))


# These examples record a tiny push dataset and train on it: the slow tier.
RECORDING_EXAMPLES = {"mmf_rl.train", "mmf_rl.evaluate"}


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(name, marks=pytest.mark.slow) if name in RECORDING_EXAMPLES else name
        for name in WITH_EXAMPLES
    ],
)
def test_examples_run(name):
    with torch.random.fork_rng(devices=[]):  # an example that seeds torch leaves the other tests' draws alone
        count, failures = run_examples(PUBLIC[name], name)
    assert count > 0
    assert failures == "", failures


# --- the checks themselves fail where they should ---------------------------------------------------

FAKE_MODULE = '''
def complete(x: int, *, scale: float = 1.0) -> float:
    """Scale a number.

    Args:
        x (int): the number.

    Keyword Args:
        scale (float, optional): the factor. Defaults to ``1.0``.

    Returns:
        ``x * scale``.

    Raises:
        ValueError: when ``x`` is negative.

    Examples:
        >>> from fake_api import complete
        >>> complete(2, scale=1.5)
        3.0
    """
    if x < 0:
        raise ValueError("negative")
    return x * scale


def without_args(x):
    """Double a number."""
    return 2 * x


def without_type(x):
    """Double a number.

    Args:
        x: the number.

    Returns:
        Twice ``x``.
    """
    return 2 * x


def stale_args(x):
    """Double a number.

    Args:
        y (int): the number.

    Returns:
        Twice ``x``.
    """
    return 2 * x


def without_returns(x):
    """Double a number.

    Args:
        x (int): the number.
    """
    return 2 * x


def without_raises(x):
    """Check a number.

    Args:
        x (int): the number.
    """
    if x < 0:
        raise ValueError("negative")


class WithoutArgs:
    """A box."""

    def __init__(self, value):
        self.value = value


def wrong_example():
    """Two.

    Returns:
        Two.

    Examples:
        >>> from fake_api import wrong_example
        >>> wrong_example()
        3
    """
    return 2
'''


@pytest.fixture
def fake_module(tmp_path, monkeypatch):
    (tmp_path / "fake_api.py").write_text(FAKE_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("fake_api", None)
    yield importlib.import_module("fake_api")
    sys.modules.pop("fake_api", None)


@pytest.mark.parametrize(
    "name, problem",
    [
        ("without_args", "has no Args: section"),
        ("without_type", "is not `name (type): description`"),
        ("stale_args", "documents ['y'], which are not parameters"),
        ("without_returns", "has no Returns: section"),
        ("without_raises", "has no Raises: section"),
        ("WithoutArgs", "has no Args: section"),
    ],
)
def test_docstring_check_flags_what_is_missing(fake_module, name, problem):
    assert docstring_problems(fake_module.complete) == []
    problems = docstring_problems(getattr(fake_module, name))
    assert any(problem in p for p in problems), problems


def test_example_runner_flags_a_wrong_output(fake_module):
    assert run_examples(fake_module.complete, "complete") == (2, "")
    count, failures = run_examples(fake_module.wrong_example, "wrong_example")
    assert count == 2 and "Expected:\n    3\nGot:\n    2" in failures


def test_exported_lists_the_all_of_a_package_and_the_public_defs_of_a_module(fake_module):
    assert set(exported(fake_module)) == {
        f"fake_api.{n}"
        for n in (
            "complete",
            "without_args",
            "without_type",
            "stale_args",
            "without_returns",
            "without_raises",
            "WithoutArgs",
            "wrong_example",
        )
    }
    assert "mmf_rl.models.MultimodalForecaster" in PUBLIC and "mmf_rl.keys.obs_key" in PUBLIC
