# skidbench: every target creates/refreshes its own virtual environment first (`setup`).
# Outputs go under $(OUT) (ignored by git).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.skidbench-installed
OUT    ?= outputs
SCALE  ?= mini
SEED   ?= 0
SOURCE ?= sim
DATA   ?=
export SKIDBENCH_OUT := $(abspath $(OUT))

SKB := $(BIN)/skidbench

.PHONY: setup reproduce test lint clean bench discover mlflow-ui

setup: $(STAMP)

# Re-installs only when pyproject.toml changes; a no-op (well under a second) otherwise.
$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check --upgrade pip
	$(BIN)/python -m pip install -q --disable-pip-version-check -e '.[dev]'
	@touch $@

reproduce: setup
	$(SKB) simulate scale=$(SCALE) seed=$(SEED)
	$(SKB) extract
	$(SKB) groundtruth
	$(SKB) split
	@echo "outputs: $(SKIDBENCH_OUT)"

test: setup
	$(BIN)/python -m pytest -q

# Performance comparisons, one process each -> benchmark/results/latest.{json,md} (BENCH="a b" for some).
bench: setup
	$(BIN)/python -m skidbench.benchmark.perf $(BENCH)

lint: setup
	$(BIN)/ruff check pipeline models benchmark tests examples
	$(BIN)/ruff format --check pipeline models benchmark tests examples

clean:
	rm -rf $(OUT) .pytest_cache .ruff_cache build *.egg-info
