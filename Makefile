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

.PHONY: setup reproduce reproduce-state readme-numbers test test-fast test-profile lint clean bench discover mlflow-ui lock system-packages

setup: $(STAMP)

# The exact versions (and hashes) of every package `setup` installs: two machines that run `make setup`
# get the same NumPy, SciPy, Numba, OpenCV..., so the same inputs give the same numbers (pyproject.toml's
# ranges alone let a fresh install resolve other versions). Made by `make lock` (pip-tools' pip-compile,
# for CPython 3.11 on Linux x86-64); every MLflow run records the lock's digest and whether the installed
# versions match it (benchmark provenance). LOCK= (empty) installs from pyproject.toml's ranges instead.
LOCK ?= requirements.lock

# Re-installs only when pyproject.toml or the lock changes; a no-op (well under a second) otherwise.
$(STAMP): pyproject.toml $(LOCK)
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --disable-pip-version-check --upgrade pip
ifneq ($(LOCK),)
	$(BIN)/python -m pip install -q --disable-pip-version-check --require-hashes -r $(LOCK)
	$(BIN)/python -m pip install -q --disable-pip-version-check --no-deps -e .
else
	$(BIN)/python -m pip install -q --disable-pip-version-check -e '.[dev]'
endif
	@touch $@

# `make lock`: the lock again from pyproject.toml, keeping its pinned versions where they still fit (a new
# dependency gets the newest allowed); `make lock UPGRADE=1`: every package at the newest version allowed
# (then re-measure the README's and docs' tables). pip-tools runs in its own venv, not the project's.
PIPTOOLS := .venv-lock
UPGRADE ?=
lock:
	@test -x $(PIPTOOLS)/bin/pip-compile || { $(PYTHON) -m venv $(PIPTOOLS) && \
		$(PIPTOOLS)/bin/python -m pip install -q --disable-pip-version-check 'pip-tools>=7.4,<8'; }
	$(PIPTOOLS)/bin/pip-compile -q --allow-unsafe --extra=dev --generate-hashes --no-emit-find-links \
		--no-emit-index-url --no-emit-trusted-host --strip-extras $(if $(UPGRADE),--upgrade) \
		--output-file=requirements.lock pyproject.toml

# `make reproduce`: the built-in simulated dataset; evaluate prints the leaderboard under the paper's
# commanded inputs, then under the calibrated wheel response (inputs=response; a dataset without wheel
# encoders says so in one line and skips it), compare sets the protocols side by side. The two evaluates
# run at the same time (pipeline/runner/side_by_side.py: they write apart; the second's output is printed after
# the first's), the same files and MLflow records as one after the other in the time of the longer one.
# `make reproduce SOURCE=amrl_txt|bag|drive_df DATA=<dir>`: the same benchmark on your data (no simulation). Every stage gets the same source arguments, plus any
# Hydra overrides in ARGS (e.g. ARGS="robot=husky source.file=husky_windows.parquet").
ARGS ?=
ifeq ($(SOURCE),sim)
SRC_ARGS := scale=$(SCALE) seed=$(SEED) $(ARGS)
else
SRC_ARGS := source=$(SOURCE) source.root=$(abspath $(DATA)) $(ARGS)
endif

reproduce: setup
ifeq ($(SOURCE),sim)
	$(SKB) simulate $(SRC_ARGS)
else
	@test -n "$(DATA)" || { echo "make reproduce SOURCE=$(SOURCE) needs DATA=<folder with the data>"; exit 2; }
endif
	$(SKB) extract $(SRC_ARGS)
	$(SKB) groundtruth $(SRC_ARGS)
	$(SKB) split $(SRC_ARGS)
	$(SKB) calibrate $(SRC_ARGS)
	$(BIN)/python -m skidbench.pipeline.runner.side_by_side \
		$(SKB) evaluate $(SRC_ARGS) :: $(SKB) evaluate $(SRC_ARGS) inputs=response
	$(SKB) compare $(SRC_ARGS)

# `make reproduce-state` after `make reproduce` (the same SCALE/SOURCE/DATA/ARGS): the state protocol's
# evaluate (each window from the robot's state, docs/plugins.md section 9) of every model and the two
# dynamics models at the horizons of the error-against-horizon curve (the 6 s board first), then compare
# (reports/horizons.md: error against horizon by aggressiveness). The other models' fits are the commanded
# evaluate's (the same fit files).
STATE_ARGS ?= 'models=[ideal,edd,full_linear,roc,enhanced,friction,drive_blr,gp_residual,relax,state_ridge]'

reproduce-state: setup
	$(SKB) evaluate $(SRC_ARGS) inputs=state $(STATE_ARGS)
	$(SKB) compare $(SRC_ARGS)

# `make readme-numbers OUT=<dir>` after `make reproduce OUT=<dir>` (a fresh root, the default mini scale):
# the record of that run's leaderboards (docs/results/reproduce-mini.json: per protocol and model the
# README's four numbers, with the run ids, commit and versions) and the README block to paste after its
# marker; tests/test_readme_numbers.py checks the README against the record.
readme-numbers: setup
	$(BIN)/python tests/readme_numbers.py $(OUT)

# `make discover`: discrepancy discovery from the extended differential drive (model=edd) on the same data
# (default: the simulated mini dataset) -> $(OUT)/<dataset>/discovery/{discovery.json,discovery.png}; then
# the benchmark scores the base and the discovered model (fitted on Train, scored on CV/LD) side by side.
discover: setup
ifeq ($(SOURCE),sim)
	$(SKB) simulate $(SRC_ARGS)
else
	@test -n "$(DATA)" || { echo "make discover SOURCE=$(SOURCE) needs DATA=<folder with the data>"; exit 2; }
endif
	$(SKB) extract $(SRC_ARGS)
	$(SKB) groundtruth $(SRC_ARGS)
	$(SKB) split $(SRC_ARGS)
	$(SKB) calibrate $(SRC_ARGS)
	$(SKB) discover $(SRC_ARGS) model=edd
	$(SKB) evaluate $(SRC_ARGS) 'models=[edd,discovered]'
	$(SKB) compare $(SRC_ARGS) figures.enabled=false

# The MLflow UI on the local store (the one evaluate/compare use unless MLFLOW_TRACKING_URI is set). First
# prints, per dataset, the page to open: the runs of its latest evaluate with the RMSRE columns.
mlflow-ui: setup
	@$(BIN)/python -c 'from skidbench.benchmark.tracking.mlflow_ui import print_ui_links as p; \
		p("sqlite:///$(SKIDBENCH_OUT)/mlflow.db", "http://127.0.0.1:5000")'
	$(BIN)/mlflow ui --backend-store-uri sqlite:///$(SKIDBENCH_OUT)/mlflow.db --port 5000

# The Ray tests need the optional `cluster` extra: installed best-effort, once per pyproject.toml change;
# where it cannot be installed those tests are skipped with the reason.
CLUSTER_STAMP := $(VENV)/.skidbench-cluster
# The lock's pins as constraints without their hashes (pip refuses a requirement without a hash beside hashed
# constraints): the extra's own packages resolve freely, everything the lock pins keeps its version.
CONSTRAINTS := $(VENV)/constraints.txt
$(CONSTRAINTS): $(STAMP)
	grep -E '^[A-Za-z0-9_.-]+==' $(LOCK) | sed 's/ *\\$$//' > $@
# An extra's own packages (pyproject.toml's optional-dependencies), not the project again: `setup` installed
# it already, and each editable install builds it anew (a build environment fetched from the index and four
# build-backend calls; 2-3 min of a `make test` on a loaded machine, 2026-11-27).
EXTRA_REQS = $(BIN)/python -c 'import sys, tomllib; \
	print("\n".join(tomllib.load(open("pyproject.toml", "rb"))["project"]["optional-dependencies"][sys.argv[1]]))'
$(CLUSTER_STAMP): $(STAMP) $(if $(LOCK),$(CONSTRAINTS))
	$(EXTRA_REQS) cluster > $(VENV)/extra-cluster.txt
	$(BIN)/python -m pip install -q --disable-pip-version-check $(if $(LOCK),-c $(CONSTRAINTS)) -r $(VENV)/extra-cluster.txt \
		|| echo "make test: the cluster extra (Ray) did not install; its tests will be skipped"
	@touch $@

# The tests of a lab's MLflow server (PostgreSQL behind `mlflow server`, tests/mlflow_server.py) and of its
# UI (headless Chromium, tests/test_mlflow_ui_browser.py) need two Debian packages, `postgresql` and
# `chromium`: installed here, where missing, when make runs as root with apt-get (a fresh CI machine);
# best-effort: where they cannot be installed those tests skip with the reason. A cheap check when both
# are there. The `server` extra (psycopg, the PostgreSQL driver): once per pyproject.toml change, every
# package the lock pins kept at its version (as the cluster extra's).
SERVER_STAMP := $(VENV)/.skidbench-server
system-packages:
	@missing=""; \
	ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1 || command -v initdb >/dev/null || missing="postgresql"; \
	command -v chromium >/dev/null || test -x /usr/bin/chromium || missing="$$missing chromium"; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
		echo "make test: installing the Debian packages $$missing (apt-get)"; \
		{ apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $$missing; } >/dev/null \
			|| echo "make test: apt-get could not install $$missing; the tests that need it will be skipped"; \
	else \
		echo "make test: $$missing not installed (installing needs root and apt-get); the tests that need it will be skipped"; \
	fi
$(SERVER_STAMP): $(STAMP) $(if $(LOCK),$(CONSTRAINTS))
	$(EXTRA_REQS) server > $(VENV)/extra-server.txt
	$(BIN)/python -m pip install -q --disable-pip-version-check $(if $(LOCK),-c $(CONSTRAINTS)) -r $(VENV)/extra-server.txt \
		|| echo "make test: the server extra (psycopg) did not install; the PostgreSQL tests will be skipped"
	@touch $@

# The suite on two workers (pytest-xdist). Work units (tests/conftest.py `xdist_unit`): a test file, so
# that its shared fixtures (a simulated dataset, an MLflow store) are built once; the files that share a
# session fixture (the README's `make reproduce`, built once under a file lock) as one unit; the long
# independent discovery tests one by one. `make test-fast`: the unit tests only (no test marked slow: no
# end-to-end pipelines, sweeps, virtual environments or browsers), for the edit loop.
PYTEST := $(BIN)/python -m pytest -q -n 2 --dist loadgroup
test: setup $(CLUSTER_STAMP) $(SERVER_STAMP) system-packages
	$(PYTEST)

test-fast: setup
	$(PYTEST) -m "not slow"

# `make test`'s suite with each test's CPU seconds recorded -> perf/results/test_suite.md (perf/test_suite.py)
test-profile: setup $(CLUSTER_STAMP) $(SERVER_STAMP) system-packages
	$(BIN)/python -m perf.test_suite perf/results/test_suite.md -q -n 2 --dist loadgroup

# Performance comparisons, one process each -> perf/results/latest.{json,md} (BENCH="a b" for some).
# perf/ is not installed (it measures the package from outside): run from the repository root.
bench: setup
	$(BIN)/python -m perf $(BENCH)

lint: setup
	$(BIN)/ruff check pipeline models benchmark perf hydra_plugins tests examples
	$(BIN)/ruff format --check pipeline models benchmark perf hydra_plugins tests examples
	$(BIN)/python -m pytest -q tests/test_layers.py  # imports go down only, no cycles (CONTRIBUTING.md)

clean:
	rm -rf $(OUT) .pytest_cache .ruff_cache build *.egg-info $(PIPTOOLS)
