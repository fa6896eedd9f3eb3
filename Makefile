# Two entry points (README): `make train` installs and trains the default task; `make test`
# installs and runs the whole test suite (what .ci/run calls). VENV picks the virtual env folder.
VENV ?= .venv
PY := $(VENV)/bin/python
TASK ?= gym/pendulum
PYTEST_ARGS ?=

.PHONY: install install-test train test lint bench

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first and pinned: any other resolution pulls CUDA wheels (see pyproject.toml).
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e '.[test]'
	touch $@

install: $(VENV)/.installed

train: install
	$(PY) main.py $(TASK)

test: install
	$(PY) -m pytest $(PYTEST_ARGS)

lint: install
	$(PY) -m ruff check .
	$(PY) -m mypy algorithm envs ds main.py main_ds.py

bench: install
	$(PY) -m pip install --quiet -e '.[test,bench]'
	bash bench/torchrl_setup.sh $(VENV)
	$(PY) -m bench.learner
	$(PY) -m bench.replay
