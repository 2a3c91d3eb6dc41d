"""A real `mlflow server` on 127.0.0.1 for tests, on a SQLite file or on a PostgreSQL cluster of its own: one
home for starting them, waiting until they answer and stopping them by PID.

PostgreSQL (a lab's set-up, docs/scaling.md): Debian's ``postgresql`` package (``make test`` installs it
where missing when run as root); :func:`postgres_missing` says why it cannot run here (the tests skip with
that line). :func:`running_postgres` runs ``initdb`` into a fresh folder and ``pg_ctl start`` on a free
loopback port, as the ``postgres`` user when the tests run as root (PostgreSQL refuses root), creates the
database ``mlflow`` and yields the SQLAlchemy URI ``mlflow server --backend-store-uri`` takes and its log."""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_gone(pid: int, timeout_s: float) -> bool:
    """True once process ``pid`` no longer exists (or is a zombie of another parent), False at the timeout."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        with contextlib.suppress(OSError):
            if Path(f"/proc/{pid}/stat").read_text().split(") ")[-1].startswith("Z"):
                return True
        time.sleep(0.2)
    return False


class MlflowServer:
    """``mlflow server`` with its backend store ``backend_uri`` (default: a SQLite file under ``root``) and
    its artifacts in ``root/artifacts``, on a loopback port that stays the same across :meth:`start` calls
    (a restarted server is the same server to its clients)."""

    def __init__(self, root: Path, backend_uri: str | None = None, port: int | None = None) -> None:
        self.root = Path(root)
        self.backend_uri = backend_uri or f"sqlite:///{self.root / 'server.db'}"
        self.port = port or free_port()
        self.uri = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen | None = None
        self.log_path = self.root / "server.log"
        self.db_log: Path | None = None  # the database server's log, when there is one

    def start(self, timeout_s: float = 120.0) -> str:
        cmd = [
            str(Path(sys.executable).with_name("mlflow")), "server", "--host", "127.0.0.1",
            "--port", str(self.port), "--workers", "1", "--backend-store-uri", self.backend_uri,
            "--artifacts-destination", str(self.root / "artifacts"),
        ]  # fmt: skip
        with open(self.log_path, "ab") as log:
            # no job execution (MLflow's GenAI jobs: one more process for nothing here)
            env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
            self.proc = subprocess.Popen(
                cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, cwd=self.root, env=env
            )
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with urllib.request.urlopen(self.uri + "/health", timeout=2) as r:
                    if r.status == 200:
                        return self.uri
            except OSError:
                pass
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail(f"mlflow server did not start: {self.log_path.read_text()[-2000:]}")
            time.sleep(0.5)

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        """SIGKILL its process group (an outage: the server is gone without a word)."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        os.killpg(self.proc.pid, signal.SIGTERM)
        try:
            self.proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            self.kill()


@contextlib.contextmanager
def running_mlflow_server(
    root: Path, timeout_s: float = 120.0, backend_uri: str | None = None
) -> Iterator[str]:
    """Start `mlflow server` with its store under ``root`` (or ``backend_uri``); yield its URI; stop it."""
    server = MlflowServer(root, backend_uri)
    try:
        yield server.start(timeout_s)
    finally:
        server.stop()


# -- PostgreSQL -----------------------------------------------------------------------------------------
def postgres_bin(name: str) -> str | None:
    """``initdb``, ``pg_ctl``, ...: Debian keeps them in /usr/lib/postgresql/<version>/bin (the newest
    version wins), off PATH; else PATH."""
    found = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), key=lambda p: int(Path(p).parts[4]))
    return found[-1] if found else shutil.which(name)


def postgres_missing() -> str | None:
    """Why PostgreSQL cannot be run here (one line), or None."""
    if not (postgres_bin("initdb") and postgres_bin("pg_ctl")):
        return (
            "PostgreSQL is not installed (no initdb/pg_ctl; `make test` installs the Debian package "
            "postgresql when run as root)"
        )
    try:
        import psycopg  # noqa: F401
    except ImportError:
        return "the PostgreSQL driver is not installed: pip install -e '.[server]' (make test does)"
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root and there is no `postgres` user to run PostgreSQL as"
        if not shutil.which("runuser"):
            return "running as root and there is no runuser to run PostgreSQL as the postgres user"
    return None


def _as_postgres_user(cmd: list[str]) -> list[str]:
    return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd


@contextlib.contextmanager
def running_postgres(timeout_s: float = 120.0) -> Iterator[tuple[str, Path]]:
    """A PostgreSQL cluster of its own (initdb into a fresh folder under /tmp, which the postgres user can
    reach; fsync off: test data) on 127.0.0.1:<free port>, with a database ``mlflow``. Yields
    ``(postgresql+psycopg://postgres@127.0.0.1:<port>/mlflow, its server log)``; stops the postmaster by its
    PID (SIGINT: PostgreSQL's fast shutdown) and removes the folder."""
    import psycopg

    folder = Path(tempfile.mkdtemp(prefix="skidbench-pg-"))
    data = folder / "data"
    port = free_port()
    if os.geteuid() == 0:
        pg = pwd.getpwnam("postgres")
        os.chown(folder, pg.pw_uid, pg.pw_gid)
    pid = None
    try:
        run = lambda cmd: subprocess.run(  # noqa: E731
            _as_postgres_user(cmd), capture_output=True, text=True, timeout=timeout_s, cwd=folder
        )
        done = run([postgres_bin("initdb"), "-D", str(data), "-U", "postgres", "--auth=trust", "-E", "UTF8",
                    "--no-locale", "--no-sync"])  # fmt: skip
        if done.returncode:
            pytest.fail(f"initdb failed: {done.stderr[-2000:]}")
        options = (
            f"-p {port} -k {folder} -c listen_addresses=127.0.0.1 -c fsync=off "
            "-c synchronous_commit=off -c full_page_writes=off"
        )
        log = str(folder / "postgres.log")
        done = run([postgres_bin("pg_ctl"), "-D", str(data), "-o", options, "-l", log, "-w", "-t",
                    str(int(timeout_s)), "start"])  # fmt: skip
        if done.returncode:
            text = Path(log).read_text()[-2000:] if Path(log).exists() else ""
            pytest.fail(f"pg_ctl start failed: {done.stderr[-1000:]} {text}")
        pid = int((data / "postmaster.pid").read_text().split()[0])
        with psycopg.connect(
            f"host=127.0.0.1 port={port} user=postgres dbname=postgres", autocommit=True
        ) as c:
            c.execute("CREATE DATABASE mlflow")
        yield f"postgresql+psycopg://postgres@127.0.0.1:{port}/mlflow", Path(log)
    finally:
        if pid is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGINT)
            if not wait_until_gone(pid, 30):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
                wait_until_gone(pid, 10)
        shutil.rmtree(folder, ignore_errors=True)


@contextlib.contextmanager
def lab_mlflow_server(root: Path) -> Iterator[MlflowServer]:
    """The test session's one ``mlflow server`` (tests/conftest.py ``lab_server``): on a PostgreSQL cluster
    of its own (:func:`running_postgres`) where PostgreSQL can run here, else on a SQLite file under
    ``root``; started, yielded (restartable: a test may kill it) and stopped by PID."""
    with contextlib.ExitStack() as stack:
        db, db_log = (None, None) if postgres_missing() else stack.enter_context(running_postgres())
        server = MlflowServer(root, backend_uri=db)
        server.db_log = db_log  # PostgreSQL's log (what it refused: errors, duplicate keys)
        stack.callback(server.stop)
        server.start()
        yield server
