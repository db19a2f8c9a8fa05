# Fresh machine: `make demo` runs the pendulum example end to end, `make test` runs the tests.
# Both create the virtual environment in .venv and install balustrade with its extras.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# PyTorch (optional extra `learn`), pinned: an unpinned `torch` pulls a multi-GB CUDA build.
# Our machines hold the 2.13.0 CPU wheel locally, so pip takes it. On plain PyPI (Linux) the
# pinned version is still the CUDA build: set TORCH_INDEX to PyTorch's CPU index, e.g.
#   make setup TORCH_INDEX=https://download.pytorch.org/whl/cpu
TORCH ?= torch==2.13.0
TORCH_INDEX ?=

.PHONY: setup demo test test-slow bench lint docs clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)" $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
	$(PY) -m pip install -q -e ".[learn,test]"
	touch $@

setup: $(VENV)/.installed

# the `docs` extra (mkdocs + mkdocstrings), installed on first `make docs`
$(VENV)/.docs-installed: $(VENV)/.installed
	$(PY) -m pip install -q -e ".[docs]"
	touch $@

demo: setup
	$(VENV)/bin/balustrade demo --out out/demo

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	$(VENV)/bin/balustrade bench

lint: setup
	$(VENV)/bin/ruff check balustrade tests benchmarks docs/_ext audits

# API reference from the docstrings plus docs/*.md into site/; --strict turns every warning
# (a broken cross-reference, a page missing from mkdocs.yml) into a failure. Not -q: quiet mode
# hides the warnings from the strict count.
docs: $(VENV)/.docs-installed
	$(VENV)/bin/mkdocs build --strict

clean:
	rm -rf $(VENV) out site .pytest_cache
