# Two entry points (README): `make train` installs and trains the default task; `make test`
# installs and runs the whole test suite (what .ci/run calls). VENV picks the virtual env folder.
VENV ?= .venv
PY := $(VENV)/bin/python
TASK ?= gym/pendulum
PYTEST_ARGS ?=
# Two pytest workers (pytest-xdist): the tests that start several role processes run one after the
# other on one of them (tests/workers.py, SERIAL), the rest on whichever is free. PYTEST_WORKERS= runs
# the suite in one process, as a plain `pytest` does.
PYTEST_WORKERS ?= -n 2 --dist loadgroup

.PHONY: install install-test train test lint bench image-test lock

# Everything from the lock files of requirements/ (exact versions and hashes; requirements/update.sh
# writes them), in the order of the Dockerfile's test target: torch's CPU build first, alone (the one
# package from the PyTorch CPU index), the runtime set, the test extra, then this checkout as an
# editable package without resolving anything.
LOCKS := requirements/torch-cpu.txt requirements/runtime.txt requirements/test.txt

$(VENV)/.installed: pyproject.toml $(LOCKS)
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --require-hashes --no-deps -r requirements/torch-cpu.txt
	$(PY) -m pip install --quiet --require-hashes -r requirements/runtime.txt
	$(PY) -m pip install --quiet --require-hashes -r requirements/test.txt
	$(PY) -m pip install --quiet --no-deps --no-build-isolation -e .
	$(PY) -m pip check
	touch $@

install: $(VENV)/.installed

train: install
	$(PY) main.py $(TASK)

test: install
	@if [ -n "$(strip $(PYTEST_WORKERS))" ] && ! $(PY) -c 'import xdist' 2>/dev/null; then \
		echo "pytest-xdist is missing from $(VENV) (PYTEST_WORKERS needs it): rm $(VENV)/.installed; make install VENV=$(VENV)"; \
		echo "  or run the suite in one process: make test PYTEST_WORKERS="; exit 2; fi
	$(PY) -m pytest $(PYTEST_WORKERS) $(PYTEST_ARGS)

lint: install
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m mypy algorithm envs ds bench main.py main_ds.py cli.py

bench: install
	$(PY) -m pip install --quiet -e '.[test,bench]'
	bash bench/torchrl_setup.sh $(VENV)
	$(PY) -m bench.learner
	$(PY) -m bench.replay

# Builds the CPU image and runs it as docs/deploy.md documents (podman or docker; skips without either).
image-test:
	bash tests/image_smoke.sh

# Rewrites the lock files of requirements/ from pyproject.toml (keeps locked versions; UPGRADE=--upgrade moves them).
lock:
	bash requirements/update.sh $(UPGRADE)
