# metricslam — the two commands a newcomer needs: `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: install install-dev lint results test demo clean images-smoke

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) (Python 3.11) on PATH"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Extras per component (pyproject.toml). A bare `pip install -e .` is the core and
# `metricslam run`; `make demo` also needs both services, the renderer and the plots.
RUNTIME_EXTRAS := depth-service,slam-service,synth,plots
# Tests need every extra: the runtime ones, the dev tools, training (torch CPU wheel, pinned), viz
# (rerun-sdk, so the live-view recording test runs) and ros (rosbags, mcap: the ROS 2 bridge and
# MCAP recording tests).
DEV_EXTRAS := dev,$(RUNTIME_EXTRAS),train,viz,ros

# Runtime install: the project (editable) and the runtime extras; no torch.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[$(RUNTIME_EXTRAS)]'
	@touch $@

install: $(STAMP)

$(VENV)/.installed-dev: $(STAMP) pyproject.toml
	$(BIN)/pip install -q -e '.[$(DEV_EXTRAS)]'
	@touch $@

install-dev: $(VENV)/.installed-dev

# Guards (STYLE.md habit 18): ruff's rule set and the import-layer contracts, both in
# pyproject.toml; zero findings, nothing excluded.
LINT_PATHS := shared cli services training bench tests deploy

lint: install-dev
	$(BIN)/ruff check $(LINT_PATHS)
	$(BIN)/lint-imports --no-cache
	$(BIN)/python -m bench.make_results --check

# README's results block and docs/results.md, generated from bench/results/*.json (habit 17)
results: install
	$(BIN)/python -m bench.make_results

test: lint
	$(BIN)/python -m pytest $(PYTEST_ARGS)

demo: install
	$(BIN)/metricslam demo

# Both container images built and started without a container engine (deploy/images_smoke.py; not
# part of `make test`): needs root, buildah and debootstrap (apt-get install buildah debootstrap
# podman), a KITTI odometry sequence (KITTI_SEQ) and PyPI from inside the builds; writes
# bench/results/images_smoke.json; `make results` renders it into docs/deployment.md.
KITTI_SEQ ?= ../shared/data/kitti_odometry/sequences/06
SMOKE_ARGS ?=
images-smoke: install
	$(BIN)/python -m deploy.images_smoke $(KITTI_SEQ) $(SMOKE_ARGS)

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
