# metricslam — the two commands a newcomer needs: `make demo` and `make test`.
SHELL := /bin/bash
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=

.PHONY: install install-dev lint results test demo clean

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null || { echo "need $(PYTHON) (Python 3.11) on PATH"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# Runtime install: the project (editable) and its runtime dependencies; no torch.
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e .
	@touch $@

install: $(STAMP)

# Tests also need the dev tools, the training extra (torch CPU wheel, pinned) and the viz extra
# (rerun-sdk, so the live-view recording test runs), and the ros extra (rosbags, mcap: the ROS 2
# bridge and MCAP recording tests).
$(VENV)/.installed-dev: $(STAMP) pyproject.toml
	$(BIN)/pip install -q -e '.[dev,train,viz,ros]'
	@touch $@

install-dev: $(VENV)/.installed-dev

# Guards (STYLE.md habit 18): ruff's rule set and the import-layer contracts, both in
# pyproject.toml; zero findings, nothing excluded.
LINT_PATHS := shared services training bench tests

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

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
