# Two commands on a fresh machine: `make demo` and `make test`. Both create or update .venv first.
PYTHON ?= python3
VENV ?= .venv
# The project's development and CI machines (CPU only, no GPU) hold torch 2.13.0's CPU build in pip's local wheel
# folder (find-links); pinned, pip installs that build instead of PyPI's default multi-GB CUDA one. Elsewhere, install
# the torch build that fits the machine into $(VENV) first (the CPU-only one without a GPU) and set TORCH_SPEC=torch.
TORCH_SPEC ?= torch==2.13.0
PY := $(VENV)/bin/python
# Tests are single-threaded; one pytest worker per core.
TEST_WORKERS ?= 2
# Two install stamps: `make demo` needs only the library with the zoo and plots; tests and lint add the test tools
# (pytest, ruff, mypy, ray, minari), so a demo machine never installs them.
STAMP := $(VENV)/.sb3-dipper-installed
TEST_STAMP := $(VENV)/.sb3-dipper-tests-installed
# The documentation tools (sphinx, its theme, myst-parser for the Markdown changelog, a packaged MathJax) and flask
# for the labelling page's API page, for `make docs`, and markdown for `make screenshots`.
DOCS_STAMP := $(VENV)/.sb3-dipper-docs-installed
export MUJOCO_GL ?= egl

.PHONY: demo test test-slow lint format venv clean docs screenshots

venv: $(STAMP)

$(STAMP): setup.py
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet -e ".[zoo,plots]"
	touch $(STAMP)

$(TEST_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e ".[zoo,plots,tests]"
	# The labelling page's browser test drives the system's headless Chromium (Debian packages).
	command -v chromium >/dev/null || (apt-get update && apt-get install -y chromium chromium-driver)
	touch $(TEST_STAMP)

$(DOCS_STAMP): $(STAMP)
	$(PY) -m pip install --quiet -e ".[zoo,plots,docs]"
	touch $(DOCS_STAMP)

demo: $(STAMP)
	$(PY) zoo_scripts/demo.py --output-dir demo_output

test: $(TEST_STAMP)
	$(PY) -m pytest -q -n $(TEST_WORKERS) --durations=15

# The site in docs/_build/html, offline: the doctest builder runs the pages' examples (tiny budgets), then the HTML
# build reuses its parsed pages; any Sphinx warning fails.
docs: $(DOCS_STAMP)
	$(PY) -m sphinx -W --keep-going -q -b doctest -d docs/_build/doctrees docs docs/_build/doctest
	$(PY) -m sphinx -W --keep-going -q -b html -d docs/_build/doctrees docs docs/_build/html

# docs/_static/screenshots/: the README and the labelling page at 1280 px wide, in the system's headless Chromium (which
# the test install brings); markdown renders the README. tests/tools/test_screenshots.py fails until they show the
# sources.
screenshots: $(TEST_STAMP) $(DOCS_STAMP)
	$(PY) zoo_scripts/screenshots.py

test-slow: $(TEST_STAMP)
	$(PY) -m pytest -q -m slow --durations=15

lint: $(TEST_STAMP)
	$(PY) -m ruff check sb3_dipper tests zoo_scripts setup.py
	$(PY) -m ruff format --check sb3_dipper tests zoo_scripts setup.py
	$(PY) -m mypy sb3_dipper zoo_scripts

format: $(TEST_STAMP)
	$(PY) -m ruff check --fix sb3_dipper tests zoo_scripts setup.py
	$(PY) -m ruff format sb3_dipper tests zoo_scripts setup.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache
