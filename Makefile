# Fresh machine: `make demo` runs the pendulum example end to end, `make test` runs the tests.
# Both create the virtual environment in .venv and install balustrade with its extras.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# PyTorch (optional extra `learn`): the CPU wheel; an unpinned `torch` pulls a multi-GB CUDA build.
TORCH ?= torch==2.13.0

.PHONY: setup demo test test-slow bench lint clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[learn,test]"
	touch $@

setup: $(VENV)/.installed

demo: setup
	$(VENV)/bin/balustrade demo --out out/demo

test: setup
	$(PY) -m pytest -q

test-slow: setup
	$(PY) -m pytest -q -m slow

bench: setup
	$(VENV)/bin/balustrade bench

lint: setup
	$(VENV)/bin/ruff check balustrade tests benchmarks

clean:
	rm -rf $(VENV) out .pytest_cache
