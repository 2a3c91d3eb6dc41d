"""A lab's set-up, for real: `mlflow server` on a PostgreSQL database (both started here, on loopback ports,
stopped by PID; tests/mlflow_server.py), two people evaluating one dataset at once from their own output
roots through it, each compare reporting its own runs, artifacts and logged models through the server, and
the server killed mid-evaluate. Skipped, with the one-line reason, where PostgreSQL cannot run."""

from __future__ import annotations

import concurrent.futures
import contextlib
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from _bench_data import compose, write_splits
from mlflow_server import free_port, postgres_missing, wait_until_gone

from skidbench.benchmark.board.app import run as run_compare

# subprocess pipelines, servers and sweeps: part of `make test`, not of `make test-fast`
pytestmark = [pytest.mark.slow, pytest.mark.skipif(bool(postgres_missing()), reason=str(postgres_missing()))]

DS = "sim-mini"
FAULTS = Path(__file__).resolve().parent / "fault_injection"
EVALUATE = ["calibrate.use=false", "log_figures=false", "horizons=[6.0]"]  # the board's horizon: no strata
OUTAGE = "skidbench-outage"


@pytest.fixture
def server(mlflow_server_up):
    """The session's ``mlflow server`` (tests/conftest.py ``lab_server``), here on its PostgreSQL cluster;
    restartable (the outage test kills it)."""
    assert mlflow_server_up.backend_uri.startswith("postgresql")
    return mlflow_server_up


def evaluate(out_root: Path, uri: str, user: str, *args: str, env: dict | None = None) -> subprocess.Popen:
    """``skidbench evaluate`` of ``user`` on the dataset under ``out_root``, through the server ``uri``."""
    e = {**os.environ, "SKIDBENCH_OUT": str(out_root), "MLFLOW_TRACKING_URI": uri, "SKIDBENCH_USER": user}
    e.update(env or {})
    cmd = [sys.executable, "-m", "skidbench.pipeline.cli.main", "evaluate", *EVALUATE, *args]
    return subprocess.Popen(cmd, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)  # fmt: skip


def finish(proc: subprocess.Popen, timeout_s: float = 600) -> tuple[int, str, str]:
    out, err = proc.communicate(timeout=timeout_s)  # a hang guard, not a timing assertion
    return proc.returncode, out, err


def test_people_starting_on_one_new_experiment_at_once_all_get_it_tagged(server):
    """The get-or-create of an experiment and its tags, by several processes at the same moment (threads
    here, each with its own client): one experiment, tagged once, every caller gets its id; a saved view
    written by all of them at once is one tag (MLflow's server reads, then inserts, an experiment tag: the
    losers of that race try again, tracking.lost_insert_race)."""
    from mlflow import MlflowClient

    from skidbench.benchmark.tracking import mlflow_ui as mu
    from skidbench.benchmark.tracking import store as trk
    from skidbench.benchmark.tracking import tags as run_tags

    name, n = "skidbench-race", 6
    start = threading.Barrier(n)

    def one(k: int) -> str:
        tracker = trk.Tracker(server.uri, name)
        start.wait(timeout=600)  # a hang guard (a loaded machine starts six clients slowly)
        exp_id = tracker.experiment_id
        start.wait(timeout=600)  # every one has it: now the same view at once
        mu.save_view(tracker.client, exp_id, "latest-race", f"view {k}", {"k": k})
        return exp_id

    with concurrent.futures.ThreadPoolExecutor(n) as pool:
        ids = list(pool.map(one, range(n)))
    exp = MlflowClient(server.uri).get_experiment_by_name(name)
    assert set(ids) == {exp.experiment_id}
    assert exp.tags[run_tags.TAG_EXPERIMENT_KIND] == run_tags.EXPERIMENT_KIND
    assert json.loads(exp.tags[mu.TAG_SAVED_VIEW + "latest-race"])["name"] in {f"view {k}" for k in range(n)}


def test_two_people_evaluate_one_dataset_at_once_and_each_compare_reports_their_own(
    server, tmp_path, monkeypatch
):
    import mlflow
    from mlflow import MlflowClient

    roots = {user: tmp_path / user for user in ("alice", "bob")}
    for root in roots.values():  # the same data, copied to two people's output roots
        write_splits(root / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    procs = {
        "alice": evaluate(roots["alice"], server.uri, "alice", "models=[ideal,edd]"),
        "bob": evaluate(roots["bob"], server.uri, "bob", "models=[edd]", "min_distance_m=2.0"),
    }
    done = {user: finish(p) for user, p in procs.items()}
    for user, (rc, out, err) in done.items():
        assert rc == 0, f"{user}: {err[-3000:]}"
        assert "View run" not in out  # MLflow's per-run console lines are quiet

    client = MlflowClient(server.uri)
    exp = client.get_experiment_by_name(f"skidbench-{DS}")  # one dataset: one experiment for the lab
    runs = client.search_runs([exp.experiment_id], "tags.`skidbench.role` != 'compare'", max_results=100)
    parents = {r.data.tags["mlflow.user"]: r for r in runs if r.data.tags["skidbench.role"] == "parent"}
    children = [r for r in runs if r.data.tags["skidbench.role"] == "child"]
    assert sorted(parents) == ["alice", "bob"]  # nothing lost, nothing twice, nothing mixed
    assert sorted((r.data.tags["mlflow.user"], r.data.tags["skidbench.model"]) for r in children) == [
        ("alice", "edd"), ("alice", "ideal"), ("bob", "edd")
    ]  # fmt: skip
    for r in [*parents.values(), *children]:
        user = r.data.tags["mlflow.user"]
        assert r.info.status == "FINISHED"
        assert r.data.tags["skidbench.out_root"] == str(roots[user])
        assert r.data.tags["skidbench.session"] == parents[user].data.tags["skidbench.session"]
    for r in children:
        assert r.data.tags["mlflow.parentRunId"] == parents[r.data.tags["mlflow.user"]].info.run_id
    assert f" {'alice'}@" in parents["alice"].info.run_name

    # artifacts and logged models go through the server (its --artifacts-destination)
    child = next(r for r in children if r.data.tags["skidbench.model"] == "edd")
    assert [a.path for a in client.list_artifacts(child.info.run_id, "windows")] == [
        "windows/tile.windows.parquet"
    ]
    assert list((server.root / "artifacts").rglob("tile.windows.parquet"))
    model_id = child.data.tags["skidbench.logged_model"]
    assert str(client.get_logged_model(model_id).status) == "READY"
    from _bench_data import sequence_table

    mlflow.set_tracking_uri(server.uri)
    monkeypatch.setenv("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    vel = mlflow.pyfunc.load_model(f"models:/{model_id}").predict(sequence_table(5, 3.0).assign(sequence="s"))
    assert list(vel.columns) == ["vx", "vy", "wz"] and len(vel) == 90

    # each compare reports its caller's own runs; one whose runs are older hears of the other's
    monkeypatch.setenv("MLFLOW_TRACKING_URI", server.uri)
    newest = {u: max(r.info.start_time for r in children if r.data.tags["mlflow.user"] == u) for u in parents}
    for user in ("alice", "bob"):
        monkeypatch.setenv("SKIDBENCH_USER", user)
        res = run_compare(compose("compare", roots[user], ["figures.enabled=false"]))
        assert res.parents == [parents[user].info.run_id]  # every row from their own evaluate
        assert ("| ideal |" in res.leaderboard_md) == (user == "alice")
        mine = [r for r in children if r.data.tags["mlflow.user"] == user]
        board = (roots[user] / DS / "reports" / "leaderboard-commanded.csv").read_text()
        for r in mine:  # compare's cells are the server's metrics
            assert f"{r.data.metrics['ld_6s_trans_rmsre_pct']:.3f}".rstrip("0") in board
        other = "bob" if user == "alice" else "alice"
        said = [n for n in res.notes if n.startswith(f"{other} evaluated this dataset after you")]
        assert len(said) == (newest[other] > newest[user])  # they evaluated after this board's newest run
        assert "report/report.md" in [a.path for a in client.list_artifacts(res.parents[0], "report")]
    # no metric logged twice: PostgreSQL refused no duplicate row of the two evaluates (MLflow's Model.log
    # copies the run's metrics so far onto the logged model; the fit's metrics are logged after it)
    assert "metric_pk" not in server.db_log.read_text()  # the metrics' (and latest metrics') unique keys


def test_a_server_killed_mid_evaluate_fails_fast_in_one_line_and_the_board_stays_one_complete_evaluate(
    server, tmp_path, monkeypatch
):
    """After a complete evaluate, a second one (force=true) loses the server while it is between two logging
    calls (the process is held at its first write of edd's outputs, eval/edd/..., its ideal run finished):
    evaluate gives up in one line naming the server, exit status 2; once the server is back, `skidbench
    runs --reap` (this machine: the process is gone) ends every run it left, KILLED with the reason it noted
    (the server stopped answering); a re-run has nothing missing; compare's board is the complete evaluate's
    alone, the killed one's finished run named and left out."""
    from mlflow import MlflowClient

    write_splits(tmp_path / DS, terrains=("tile",), counts={"train": 1, "cv": 1, "ld": 1}, duration_s=20.0)
    # an experiment of its own on the session's server: the other tests' runs are not its business
    args = ("models=[ideal,edd]", f"mlflow.experiment={OUTAGE}")
    rc, _, err = finish(evaluate(tmp_path, server.uri, "carol", *args))
    assert rc == 0, err[-3000:]
    fault = {"SKIDBENCH_FAULT": "stop@1:/eval/edd/", "PYTHONPATH": str(FAULTS)}
    proc = evaluate(tmp_path, server.uri, "carol", *args, "force=true", env=fault)
    deadline = time.monotonic() + 600
    while _state(proc.pid) != "T":  # held at the fault
        assert proc.poll() is None, proc.communicate()[1][-3000:]
        assert time.monotonic() < deadline, "evaluate never reached the model's outputs"
        time.sleep(0.5)
    server.kill()
    t0 = time.monotonic()
    os.kill(proc.pid, signal.SIGCONT)
    rc, out, err = finish(proc, 300)
    elapsed = time.monotonic() - t0
    lines = err.strip().splitlines()
    assert rc == 2, err[-3000:]
    assert lines[-1].startswith(
        f"skidbench evaluate: error: MLflow tracking server {server.uri} stopped answering"
    )
    assert "skidbench runs --reap" in lines[-1] and "Retrying" not in err and "Traceback" not in err
    print(f"evaluate exited {elapsed:.1f} s after the server was killed: {lines[-1]}")
    assert wait_until_gone(proc.pid, 10)

    server.start()
    client = MlflowClient(server.uri)
    exp = client.get_experiment_by_name(OUTAGE)
    parents = sorted(client.search_runs([exp.experiment_id], "tags.`skidbench.role` = 'parent'"),
                     key=lambda r: r.info.start_time)  # fmt: skip
    complete, killed = parents
    mine = client.search_runs([exp.experiment_id], f"tags.`mlflow.parentRunId` = '{killed.info.run_id}'")
    left = [killed, *(r for r in mine if r.info.status == "RUNNING")]
    assert {r.info.status for r in left} == {"RUNNING"} and len(left) == 2  # the parent and edd's run
    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path), "MLFLOW_TRACKING_URI": server.uri}
    reap = subprocess.run([sys.executable, "-m", "skidbench.pipeline.cli.main", "runs", "--reap"], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert reap.returncode == 0, reap.stderr[-3000:]
    assert f"{len(left)} of them marked KILLED" in reap.stdout
    for r in left:
        after = client.get_run(r.info.run_id)
        assert after.info.status == "KILLED"
        assert (
            "ended with the run open: the MLflow tracking server stopped answering (connection refused)"
            in (after.data.tags["skidbench.failure_reason"])
        )
    models = client.search_logged_models([exp.experiment_id], max_results=1000)
    assert not [m for m in models if str(m.status) == "PENDING"]

    rc, out, err = finish(evaluate(tmp_path, server.uri, "carol", *args))  # nothing changed: nothing missing
    assert rc == 0 and "skipped" in out, err[-3000:]
    monkeypatch.setenv("MLFLOW_TRACKING_URI", server.uri)
    monkeypatch.setenv("SKIDBENCH_USER", "carol")
    res = run_compare(compose("compare", tmp_path, ["figures.enabled=false", f"mlflow.experiment={OUTAGE}"]))
    assert res.parents == [complete.info.run_id]  # one complete evaluate: not the killed one's ideal run
    (gone,) = [x for x in res.left_out if x.startswith("ideal/tile: ")]
    assert f"its evaluate {killed.info.run_name} ({killed.info.run_id[:8]}) ended KILLED" in gone


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "?"


def _walkthrough() -> tuple[list[str], dict[str, str], str, str]:
    """docs/scaling.md's lab-server walkthrough as written: its two psql lines, the service unit's
    ``Environment`` and ``ExecStart``, and the health check."""
    from doc_blocks import REPO, parse_blocks

    blocks = parse_blocks(REPO / "docs" / "scaling.md")
    (setup,) = [b for b in blocks if any("CREATE ROLE" in ln for ln in b.text)]
    (unit,) = [b for b in blocks if any(ln.startswith("ExecStart=") for ln in b.text)]
    (health,) = [b for b in blocks if any(ln.startswith("curl ") for ln in b.text)]
    psql = [ln for ln in setup.text if ln.startswith("runuser -u postgres -- psql ")]
    env = dict(
        ln.removeprefix("Environment=").split("=", 1) for ln in unit.text if ln.startswith("Environment=")
    )
    (start,) = [ln.removeprefix("ExecStart=") for ln in unit.text if ln.startswith("ExecStart=")]
    (curl,) = [ln.split("#")[0].strip() for ln in health.text if ln.startswith("curl ")]
    return psql, env, start, curl


@pytest.mark.skipif(
    os.geteuid() != 0, reason="the walkthrough's commands run as root (runuser, as documented)"
)
def test_the_lab_server_walkthrough_of_the_docs_runs_as_written(server, tmp_path):
    """docs/scaling.md's walkthrough on the session's PostgreSQL (libpq's PGHOST/PGPORT point its psql at
    it): the role and database created by its two psql lines, the service's ExecStart started with its
    Environment (a free loopback port, a temporary artifacts folder, this venv's mlflow), its health check
    answering OK, and a run logged through it landing in the role's own database."""
    import psycopg
    from mlflow import MlflowClient

    psql, env, start, curl = _walkthrough()
    assert len(psql) == 2 and env == {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    assert "--workers 1" in start and "postgresql+psycopg://skidbench:<password>@localhost/skidbench" in start
    db_port = re.search(r"@127\.0\.0\.1:(\d+)/", server.backend_uri).group(1)
    password, port = "lab-secret", free_port()
    libpq = {**os.environ, "PGHOST": "127.0.0.1", "PGPORT": db_port}
    for line in psql:
        done = subprocess.run(line.replace("<password>", password), shell=True, env=libpq,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert done.returncode == 0, f"{line}: {done.stderr}"
    for a, b in ((" --port 5000", f" --port {port}"), (" --host 0.0.0.0", " --host 127.0.0.1"),
                 ("/opt/skidbench/.venv/bin/", f"{Path(sys.executable).parent}/"), ("<password>", password),
                 ("/srv/mlflow/artifacts", str(tmp_path / "artifacts"))):  # fmt: skip
        assert a in start
        start = start.replace(a, b)
    with open(tmp_path / "server.log", "wb") as log:
        proc = subprocess.Popen(shlex.split(start), env={**libpq, **env}, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True, cwd=tmp_path)  # fmt: skip
    try:
        deadline = time.monotonic() + 300  # a hang guard: the first start creates the tables
        while True:
            health = subprocess.run(curl.replace(":5000/", f":{port}/"), shell=True, capture_output=True,
                                    text=True, timeout=30)  # fmt: skip
            if health.returncode == 0 or proc.poll() is not None or time.monotonic() > deadline:
                break
            time.sleep(1)
        assert health.returncode == 0 and health.stdout.strip() == "OK", (tmp_path / "server.log").read_text()
        client = MlflowClient(f"http://127.0.0.1:{port}")
        run = client.create_run(client.create_experiment("lab-walkthrough"))
        client.log_metric(run.info.run_id, "ld_6s_trans_rmsre_pct", 2.5)
        client.set_terminated(run.info.run_id)
        dsn = f"host=127.0.0.1 port={db_port} user=skidbench password={password} dbname=skidbench"
        with psycopg.connect(dsn) as conn:  # the role's own database holds it
            got = conn.execute("SELECT value FROM metrics WHERE run_uuid = %s", (run.info.run_id,)).fetchall()
        assert got == [(2.5,)]
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=60)
