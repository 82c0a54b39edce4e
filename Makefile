# The README's two commands are `make demo` and `make test`; each sets the machine up first.
VENV_PY := .venv/bin/python
export MUJOCO_GL ?= egl

.PHONY: setup test test-fast demo bench docs

setup:
	@bash scripts/setup.sh

# pytest-xdist: TEST_WORKERS processes (one per core of the 2-core machine the budget is measured on),
# each running torch on one thread; --dist loadgroup hands out the tests one by one, keeping together
# those of one xdist_group (a file with a module-scoped fixture; tests/conftest.py). TEST_WORKERS=0
# runs in this process. --durations: every log lists the slowest tests, so the time budget can be kept.
TEST_WORKERS ?= 2
PYTEST := $(VENV_PY) -m pytest -q -n $(TEST_WORKERS) --dist loadgroup --durations=25

test: setup
	.venv/bin/ruff check .
	.venv/bin/ruff format --check .
	$(PYTEST) tests

# The fast tier, for the edit-test loop: no recordings, subprocesses, end-to-end scripts, docs build or
# long training (the tests marked `slow`, tests/conftest.py); `make test` runs those too.
test-fast: setup
	.venv/bin/ruff check .
	$(PYTEST) -m "not slow" tests

demo: setup
	$(VENV_PY) -m mmf_rl.cli demo

bench: setup
	$(VENV_PY) benchmarks/model_throughput.py

# The documentation site (mkdocs.yml, docs/) into site/; --strict: a broken link or a docstring that does
# not render fails (tests/test_docs.py builds it too).
docs: setup
	NO_MKDOCS_2_WARNING=1 $(VENV_PY) -m mkdocs build --strict
