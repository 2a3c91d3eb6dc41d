"""Shared fixtures. Tests that use ../shared/data/real skip cleanly when it is absent."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock

from skidbench.pipeline.runner.side_by_side import BLAS_THREAD_VARS  # imports no numerical library

REPO = Path(__file__).resolve().parents[1]

#: one BLAS/OpenMP thread per test process and the commands it starts (a variable already set is kept): the
#: suite runs on two xdist workers (make test), each with a core's share; two BLAS threads each (OpenBLAS's
#: default on 2 cores) oversubscribe the cores, and OpenBLAS's waiting threads spin on them. Measured on
#: four discovery tests (`pytest -n 2 tests/test_discover_hidden.py -k ...`, alternated, 2026-11-27): 55 and
#: 44 s wall, 104 and 86 CPU-s with two threads; 22 and 24 s, 41 and 45 CPU-s with one.
for _var in BLAS_THREAD_VARS:
    os.environ.setdefault(_var, "1")
# SKIDBENCH_SHARED_REAL: where the real recordings are when the checkout is not next to ../shared (a worktree)
SHARED_REAL = Path(os.environ.get("SKIDBENCH_SHARED_REAL", REPO.parent / "shared" / "data" / "real"))


def pytest_configure(config):
    """The config's resolvers (``${skidbench.dataset:...}``), registered as the CLI registers them before
    composing: tests compose configs with Hydra's compose API and read ``cfg.dataset``."""
    from skidbench.pipeline.core.layout import register_resolvers

    register_resolvers()


@pytest.fixture(scope="session")
def shared_real() -> Path:
    """../shared/data/real (real robot recordings); skips the test when absent."""
    if not SHARED_REAL.is_dir():
        pytest.skip("../shared/data/real is absent")
    return SHARED_REAL


@pytest.fixture(scope="session")
def jackal():
    """The Jackal of conf/robot/jackal.yaml."""
    from skidbench.pipeline.core.robot import load_robot

    return load_robot("jackal")


@pytest.fixture(scope="session")
def micro_root(tmp_path_factory) -> Path:
    """An output root holding the micro simulated dataset through split (tests/reliability_data.py)."""
    from reliability_data import build

    root = tmp_path_factory.mktemp("micro")
    build(root)
    return root


@pytest.fixture(scope="session")
def lab_server(tmp_path_factory):
    """The session's one ``mlflow server`` on loopback (PostgreSQL behind it where PostgreSQL can run, else
    SQLite; tests/mlflow_server.py), shared by the tests of a lab's server and of the UI (one xdist unit:
    ``XDIST_GROUPS``). A test that kills it starts it again; :func:`mlflow_server_up` makes sure it is up."""
    from mlflow_server import lab_mlflow_server

    with lab_mlflow_server(tmp_path_factory.mktemp("lab_server")) as server:
        yield server


@pytest.fixture(scope="session")
def ray_cluster():
    """The session's one local Ray cluster (tests/ray_cluster.py: a head and a worker node, one CPU each),
    shared by the Ray sweeps and the data stages on Ray (one xdist unit: ``XDIST_GROUPS``). A test that
    adds a node kills it before it ends; the one that does runs last (tests/test_cluster_stages.py)."""
    from ray_cluster import running_ray_cluster

    with running_ray_cluster() as cluster:
        yield cluster


@pytest.fixture
def mlflow_server_up(lab_server):
    """:func:`lab_server`, running (started again when an earlier test killed it and failed before its
    restart)."""
    if not lab_server.running():
        lab_server.start()
    return lab_server


@pytest.fixture(scope="session", autouse=True)
def _fresh_sqlite_stores_from_one_migration(tmp_path_factory):
    """A new local MLflow store (SQLite: every test's fresh output root) is made by MLflow running its whole
    chain of schema migrations, seconds each time (15.3 s on this loaded machine, 0.2 s for a copy of a
    migrated file; 2026-11-25). In the test process the first new store migrates a template once; every
    later one is a copy of it (sqlite3's backup into the new file: the same tables at the same revision),
    then MLflow goes on as usual (its schema check, the Default experiment). Subprocesses are untouched."""
    import sqlite3
    import threading

    import mlflow.store.db.utils as dbu
    import sqlalchemy

    migrate, lock = dbu._initialize_tables, threading.Lock()
    template = tmp_path_factory.mktemp("mlflow-template") / "mlflow.db"

    def initialize(engine) -> None:
        if engine.dialect.name != "sqlite":
            return migrate(engine)
        with lock:
            if not template.exists():
                once = sqlalchemy.create_engine(f"sqlite:///{template}")
                migrate(once)
                once.dispose()
        with engine.connect() as conn, contextlib.closing(sqlite3.connect(template)) as src:
            src.backup(conn.connection.dbapi_connection)

    mp = pytest.MonkeyPatch()
    mp.setattr(dbu, "_initialize_tables", initialize)
    yield
    mp.undo()


@pytest.fixture(autouse=True)
def _no_inherited_mlflow_store(monkeypatch):
    """Each test starts without MLFLOW_TRACKING_URI: compare's ``mlflow.set_tracking_uri`` exports it for
    the rest of the process, and `make` or a user may have it set; a test that wants a store sets it."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)


# -- built once per test session, shared by the xdist workers ------------------------------------------
def once_per_session(tmp_path_factory, name: str, build: Callable[[Path], dict]) -> tuple[Path, dict]:
    """``build(<root>)`` run once per test session in a fresh folder ``<root>``; returns ``(root, what build
    returned)`` (JSON-able). The pytest-xdist workers are separate processes: the first to ask builds under a
    file lock in the session's temporary folder (the workers' basetemps' parent), the others wait and read
    its result; without xdist, the session's own basetemp. A build that raised leaves no result, so the
    next worker builds again (the error is its own)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    base = tmp_path_factory.getbasetemp().parent if worker else tmp_path_factory.getbasetemp()
    root, result = base / name, base / f"{name}.json"
    with FileLock(str(base / f"{name}.lock")):
        if not result.is_file():
            shutil.rmtree(root, ignore_errors=True)  # a build that raised part-way
            root.mkdir()
            result.write_text(json.dumps(build(root)))
    return root, json.loads(result.read_text())


@pytest.fixture(scope="session")
def readme_reproduce(tmp_path_factory) -> dict:
    """The README's quick start (``make reproduce``, as written, on the tiny simulated dataset) executed once
    per session in a fresh output root: ``{"root": <root>, "results": [one dict per command: n, cmd,
    returncode, stdout, stderr]}``. tests/test_docs_commands.py asserts that it succeeds,
    tests/test_e2e.py what it wrote (the MLflow runs, fits, calibration and report). Read only: a test
    that changes an output root makes its own."""
    from doc_blocks import doc_env, quickstart, run_block

    root, results = once_per_session(
        tmp_path_factory, "readme_reproduce", lambda out: run_block(quickstart(), doc_env(out))
    )
    return {"root": root, "results": results}


@pytest.fixture(scope="session")
def publishing_walkthrough(readme_reproduce, tmp_path_factory) -> dict:
    """docs/publishing.md's walkthroughs (its ``run`` blocks in order: the quick start's dataset exported to
    ``release/public`` and ``release/private``; the public half imported into ``lab-b``, the ideal model's
    predictions written by examples/predict_ideal.py and checked there; both halves imported into
    ``board``, the predictions scored, compared and published there) executed once per session on the
    quick start's root (read only), in one folder of their own (``$TMP``, the blocks' cwd): ``{"tmp":
    <folder>, "results": [one dict per command, as readme_reproduce's, with its block's id]}``, up to the
    first that fails. tests/test_docs_commands.py asserts that they succeed, tests/test_release.py what they
    wrote."""
    from doc_blocks import doc_env, publishing, run_block

    quick = Path(readme_reproduce["root"])

    def run(tmp: Path) -> list[dict]:
        results: list[dict] = []
        for block in publishing():
            got = [{**r, "block": block.id} for r in run_block(block, {**doc_env(quick), "TMP": str(tmp)})]
            results += got
            if any(r["returncode"] for r in got):
                break
        return results

    tmp, results = once_per_session(tmp_path_factory, "publishing_walkthrough", run)
    return {"tmp": tmp, "results": results}


# -- pytest-xdist: which tests share a worker (make test: -n 2 --dist loadgroup) ------------------------
#: files whose tests share a session fixture: one worker runs them all, so it is built once and no worker
#: waits for the other's build (README quick start: test_docs_commands and test_e2e; the micro dataset)
XDIST_GROUPS = {
    "tests/test_docs_commands.py": "readme_reproduce",
    "tests/test_e2e.py": "readme_reproduce",
    "tests/test_release.py": "readme_reproduce",
    "tests/test_readme_numbers.py": "readme_reproduce",
    "tests/test_datasets_home.py": "micro_root",
    "tests/test_reliability_determinism.py": "micro_root",
    "tests/test_reliability_faults.py": "micro_root",
    "tests/test_reliability_sweeps.py": "micro_root",
    "tests/test_mlflow_server.py": "lab_server",
    "tests/test_mlflow_ui_browser.py": "lab_server",
    "tests/test_cluster_ray.py": "ray_cluster",
    "tests/test_cluster_stages.py": "ray_cluster",
}
#: files of long, independent tests (no module fixture): one test per unit, so they balance over workers
XDIST_SPREAD = ("tests/test_discover_hidden.py", "tests/test_discover_terms.py")
_NAMES = "tests/test_discover_hidden.py::test_discover_names_the_hidden_effect_alone_and_shrinks_the_gap"
#: tests that assert different things of one discovery run (tests/discover_data.py ``discovered``, made once
#: per process): one unit per run, so one worker makes it
XDIST_SHARED = {
    f"discovered:{world}": tests
    for world, tests in {
        "angular_acceleration_slip": (
            f"{_NAMES}[angular_acceleration_slip]",
            "tests/test_discover_hidden.py::test_a_placebo_names_nothing",
            "tests/test_discover_terms.py::test_catalogue_effect_keeps_its_catalogue_name_against_the_terms",
        ),
        "actuator_lag": (
            f"{_NAMES}[actuator_lag]",
            "tests/test_discover_protocol.py::"
            "test_actuator_lag_is_named_under_commanded_and_not_again_under_response",
        ),
        "none": (
            "tests/test_discover_hidden.py::test_discover_finds_no_missing_effect_when_there_is_none[7]",
            "tests/test_discover_terms.py::test_noise_only_data_names_nothing_and_reports_the_residual_unexplained",
        ),
    }.items()
}


def docs_blocks_alone() -> tuple[str, ...]:
    """The documented run blocks that use no session fixture of their file's group (neither the quick start
    nor its root; the README's own-data block: `make reproduce` on the AMRL fixture): long, so each is a
    unit of its own, run beside the group instead of after it."""
    from doc_blocks import BLOCKS, quickstart

    return tuple(
        f"tests/test_docs_commands.py::test_documented_blocks_run_as_written[{b.id}]"
        for b in BLOCKS
        if b.mode == "run" and b.id != quickstart().id and b.opts["root"] != "quickstart"
    )


XDIST_ALONE = docs_blocks_alone()
#: the longest units start first (longest-processing-time-first), the rest in xdist's order (most tests
#: first). Measured with --durations=40 on 2026-11-24: the quick start and discover_hidden's
#: curvature_dependent_icr case are the two longest units; the lab's server and its UI (one PostgreSQL, one
#: mlflow server, two evaluates in subprocesses, an outage, three pages in Chromium) took 4 min 12 s alone
#: on 2026-11-25 (pytest tests/test_mlflow_server.py tests/test_mlflow_ui_browser.py, the machine loaded).
#: The README's own-data block (`make reproduce` on the AMRL fixture) was the third-longest test of
#: `make test --durations=80` on 2026-11-25 (462 s, the machine loaded; the quick start and curvature
#: over 1800 s). A per-test clock over `make test` on 2026-11-27 (the machine quiet): the micro dataset's
#: group (the reliability tests and test_datasets_home) 234 s of wall, the quick start's 220 s, the lab's
#: server 66 s, test_discover_protocol's one test 30 s; the micro group started half-way through the run and
#: test_discover_protocol was among the last units.
XDIST_FIRST = (
    "readme_reproduce",
    "micro_root",
    "tests/test_discover_hidden.py::test_discover_names_the_hidden_effect_alone_and_shrinks_the_gap"
    "[curvature_dependent_icr]",
    *XDIST_ALONE,
    "lab_server",
    "discovered:actuator_lag",
)


def xdist_unit(nodeid: str) -> str:
    """The work unit of a test under ``--dist loadgroup``: its file (as ``--dist loadfile``: a file's module
    fixtures are built once), its group (``XDIST_GROUPS``), its shared discovery (``XDIST_SHARED``) or, in
    ``XDIST_SPREAD`` or ``XDIST_ALONE``, the test itself."""
    shared = [unit for unit, tests in XDIST_SHARED.items() if nodeid in tests]
    if shared:
        return shared[0]
    path = nodeid.split("::")[0]
    if path in XDIST_SPREAD or nodeid in XDIST_ALONE:
        return nodeid
    return XDIST_GROUPS.get(path, path)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadgroup``: units of :func:`xdist_unit` (pytest-xdist's own loadgroup reads ``xdist_group``
    marks by renaming node ids, which pytest 9.2 ignores, so it distributes test by test)."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class UnitScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_unit(nodeid)

        def _assign_work_unit(self, node) -> None:
            for unit in reversed(XDIST_FIRST):
                if unit in self.workqueue:
                    self.workqueue.move_to_end(unit, last=False)
            super()._assign_work_unit(node)

    return UnitScheduling(config, log)
