# kpstudy: `make reproduce` and `make test` set everything up from a clean clone.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PROFILE ?= quick
# System libraries of the headless renderer: EGL (glvnd + Mesa) and Mesa's llvmpipe software rasteriser.
SYSTEM_PACKAGES := libegl1 libegl-mesa0 libgl1 libgbm1 libgl1-mesa-dri
STAMP := $(VENV)/.installed

.PHONY: setup system venv neuralsat test test-fast lint docs reproduce retrain-friendly retrain-resnet bench clean

setup: system $(STAMP)

system:
	@missing=$$(for p in $(SYSTEM_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || echo $$p; done); \
	if [ -n "$$missing" ]; then \
		echo "installing system packages: $$missing"; \
		SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq --no-install-recommends $$missing; \
	fi

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

# Reinstalls only when environment.txt or pyproject.toml change (a second run installs nothing).
$(STAMP): environment.txt pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install -q --disable-pip-version-check -r environment.txt
	$(PY) -m pip install -q --disable-pip-version-check --no-deps --no-build-isolation -e .
	touch $@

# NeuralSAT in its own environment (its pins clash with kpstudy's: environment-neuralsat.txt),
# for tests/test_neuralsat.py, which skips where it is missing.
NEURALSAT_VENV := .venv-neuralsat
NEURALSAT_STAMP := $(NEURALSAT_VENV)/.installed

neuralsat: $(NEURALSAT_STAMP)

$(NEURALSAT_VENV)/bin/python:
	$(PYTHON) -m venv $(NEURALSAT_VENV)

$(NEURALSAT_STAMP): environment-neuralsat.txt | $(NEURALSAT_VENV)/bin/python
	$(NEURALSAT_VENV)/bin/python -m pip install -q --disable-pip-version-check --no-deps \
		-r environment-neuralsat.txt
	touch $@

test: setup neuralsat
	$(PY) -m pytest -q

test-fast: setup
	$(PY) -m pytest -q -m "not slow"

lint: setup
	$(VENV)/bin/ruff check kpstudy data_gen tests benchmarks docs/examples docs/api
	$(VENV)/bin/ruff format --check kpstudy data_gen tests benchmarks docs/examples docs/api

# The API reference: Sphinx + numpydoc over the docstrings (docs/api), HTML in docs/_build/html;
# any warning fails it (tests/test_api_docs.py builds it the same way). -E re-reads every
# page: an incremental build would not repeat the warnings of a page it does not re-read.
docs: setup
	$(PY) -m sphinx -b html -E -W --keep-going -q docs/api docs/_build/html
	@echo "API reference: docs/_build/html/index.html"

# The main job: everything that exists so far, at the chosen profile.
reproduce: setup
	$(PY) -m kpstudy reproduce --profile $(PROFILE)

# The same, training the verification-friendly CNN from scratch instead of using the shipped one.
retrain-friendly: setup
	$(PY) -m kpstudy reproduce --profile $(PROFILE) --retrain cnn_patch_smooth

# The same, training the ResNet-18 from scratch instead of using the shipped one (where one ships).
retrain-resnet: setup
	$(PY) -m kpstudy reproduce --profile $(PROFILE) --retrain resnet18

bench: setup
	$(PY) benchmarks/run_all.py

clean:
	rm -rf $(VENV) $(NEURALSAT_VENV) .pytest_cache .ruff_cache .hypothesis docs/_build
