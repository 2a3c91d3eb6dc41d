"""Run bookkeeping on a local store (benchmark/tracking/bookkeeping.py): which RUNNING runs `skidbench runs
--reap`
marks KILLED (a dead process of this machine; another machine's run without a recent heartbeat) and which
it leaves alone (a live process of this machine, whatever its age; another machine's run with a recent
heartbeat), the PENDING logged models it marks FAILED, and how a tracking server that does not answer is
told from one that refuses a request. The real server, killed mid-evaluate: tests/test_mlflow_server.py."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from mlflow import MlflowClient
from mlflow.entities import LoggedModelStatus

from skidbench.benchmark.tracking import bookkeeping as bk
from skidbench.benchmark.tracking import store as trk
from skidbench.benchmark.tracking.tags import (
    TAG_HEARTBEAT,
    TAG_HOST,
    TAG_PID,
    TAG_USER,
    owner_tags,
    process_tags,
    utc_now,
)


@pytest.fixture
def store(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    return client, client.create_experiment("skidbench-x", artifact_location=(tmp_path / "a").as_uri())


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_reap_ends_the_runs_whose_process_is_gone_and_leaves_the_live_ones(store):
    client, exp = store
    here = process_tags()
    old = "2026-01-01T00:00:00Z"
    elsewhere = {TAG_HOST: "other-machine", "skidbench.boot_id": "b", TAG_PID: "12", TAG_USER: "bob"}
    runs = {
        "dead here": {**here, TAG_PID: str(dead_pid()), TAG_HEARTBEAT: utc_now()},
        "alive here, old beat": {**here, TAG_HEARTBEAT: old},  # this process: judged by its pid alone
        "elsewhere, old beat": {**elsewhere, TAG_HEARTBEAT: old},
        "elsewhere, fresh beat": {**elsewhere, TAG_HEARTBEAT: utc_now()},
    }
    ids = {name: client.create_run(exp, run_name=name, tags=tags).info.run_id for name, tags in runs.items()}
    model = client.create_logged_model(exp, source_run_id=ids["elsewhere, old beat"], name="m")
    finished = client.create_run(exp, run_name="finished", tags=owner_tags()).info.run_id
    orphan = client.create_logged_model(exp, source_run_id=finished, name="orphan")
    client.set_terminated(finished, "FINISHED")

    # what every stage does when it opens the store: this machine's dead processes only
    assert [r.run_id for r in bk.reap(client, [exp])] == [ids["dead here"]]
    # `skidbench runs` without --reap changes nothing, and says which have no live process
    lines = bk.runs_report(client, [client.get_experiment(exp)], False, 600.0)
    assert lines[-1].startswith("3 run(s) RUNNING in 1 skidbench experiment(s), 1 with no live process")
    assert client.get_run(ids["elsewhere, old beat"]).info.status == "RUNNING"
    # --reap: another machine's run without a heartbeat for 10 minutes, and the PENDING models
    lines = bk.runs_report(client, [client.get_experiment(exp)], True, 600.0)
    status = {name: client.get_run(i).info.status for name, i in ids.items()}
    assert status == {"dead here": "KILLED", "alive here, old beat": "RUNNING",
                      "elsewhere, old beat": "KILLED", "elsewhere, fresh beat": "RUNNING"}  # fmt: skip
    reason = client.get_run(ids["elsewhere, old beat"]).data.tags["skidbench.failure_reason"]
    assert "on other-machine is gone or cut off" in reason and "> 600 s" in reason
    assert client.get_logged_model(model.model_id).status == LoggedModelStatus.FAILED
    assert client.get_logged_model(orphan.model_id).status == LoggedModelStatus.FAILED
    assert (
        lines[-1]
        == "3 run(s) RUNNING, 1 of them marked KILLED; 1 PENDING logged model(s) of ended runs marked FAILED"
    )


def test_every_run_records_who_made_it_from_where_in_which_session(tmp_path, monkeypatch):
    monkeypatch.setenv("SKIDBENCH_USER", "alice")
    tracker = trk.Tracker(
        f"sqlite:///{tmp_path / 'mlflow.db'}", "skidbench-x", tmp_path / "a", out_root=tmp_path
    )
    with tracker.run("p", {}) as parent:
        child = tracker.start("c", {}, parent)
        tracker.end(child)
    a, b = (tracker.client.get_run(r).data.tags for r in (parent, child))
    assert a["mlflow.user"] == "alice" and a["skidbench.out_root"] == str(tmp_path)
    assert a["skidbench.session"] == b["skidbench.session"] and a["skidbench.pid"] == str(os.getpid())
    assert bk.why_gone(tracker.client.get_run(parent), 0.0, 1.0) is None  # a live process of this machine


def test_a_server_that_does_not_answer_is_told_from_one_that_refuses_the_request(monkeypatch):
    from mlflow.exceptions import MlflowException
    from mlflow.utils.rest_utils import MlflowHostCreds, http_request
    from mlflow_server import free_port

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
    with pytest.raises(MlflowException) as gone:
        http_request(MlflowHostCreds(f"http://127.0.0.1:{free_port()}"), "/api/2.0/mlflow/runs/get", "GET")
    assert trk.unreachable(gone.value) == "connection refused"
    assert trk.unreachable(MlflowException("Run 'x' not found")) is None


def test_skidbench_bounds_mlflows_http_retries_unless_the_user_set_them(monkeypatch):
    for key in trk.HTTP_DEFAULTS:
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_TIMEOUT", "42")
    trk.use_http_defaults()
    assert os.environ["MLFLOW_HTTP_REQUEST_TIMEOUT"] == "42"
    assert (
        os.environ["MLFLOW_HTTP_REQUEST_MAX_RETRIES"] == trk.HTTP_DEFAULTS["MLFLOW_HTTP_REQUEST_MAX_RETRIES"]
    )
    # the worst case of one request to a server that accepts and never answers: 4 tries of the timeout
    # plus the back-off (urllib3: 0, 2f, 4f, ... s, each + up to the jitter), under a minute
    d = {
        k.removeprefix("MLFLOW_HTTP_REQUEST_"): float(v)
        for k, v in trk.HTTP_DEFAULTS.items()
        if "REQUEST" in k
    }
    retries = int(d["MAX_RETRIES"])
    backoff = (
        sum(d["BACKOFF_FACTOR"] * 2 ** (k - 1) for k in range(2, retries + 1)) + retries * d["BACKOFF_JITTER"]
    )
    assert (retries + 1) * d["TIMEOUT"] + backoff < 60


def test_a_write_that_lost_an_insert_race_is_tried_again_and_any_other_refusal_is_not(tmp_path):
    """Two people tagging one new experiment (or logging one dataset) at once: MLflow's SQL store reads,
    then inserts, and the second insert fails on the row's key (the message of MLflow's server on
    PostgreSQL, as CI saw it); the row is there on the next try. Another unique key is a real error."""
    from mlflow.exceptions import MlflowException

    lost = (
        "BAD_REQUEST: (psycopg.errors.UniqueViolation) duplicate key value violates unique constraint "
        '"experiment_tag_pk" DETAIL: Key (key, experiment_id)=(mlflow.experimentKind, 1) already exists.'
    )
    for text in (lost, "(sqlite3.IntegrityError) UNIQUE constraint failed: datasets.experiment_id, x",
                 "Duplicate entry 'a-1' for key 'experiment_tags.PRIMARY'"):  # fmt: skip
        assert trk.lost_insert_race(MlflowException(text)), text
    name_taken = 'duplicate key value violates unique constraint "experiments_name_key"'
    assert not trk.lost_insert_race(MlflowException(name_taken))

    tracker = trk.Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "skidbench-x", artifact_root=tmp_path)
    calls = []

    def write(fails: int, text: str) -> str:
        calls.append(text)
        if len(calls) <= fails:
            raise MlflowException(text)
        return "done"

    assert tracker.call(write, 1, lost) == "done" and len(calls) == 2  # lost once, then the row is there
    calls.clear()
    with pytest.raises(MlflowException, match="experiment_tag_pk"):  # never resolves: bounded, then raised
        tracker.call(write, 99, lost)
    assert len(calls) == trk.CONFLICT_TRIES
    calls.clear()
    with pytest.raises(MlflowException, match="experiments_name_key"):
        tracker.call(write, 1, name_taken)
    assert len(calls) == 1


def test_a_log_of_more_than_one_call_takes_is_split_within_mlflows_limits_and_loses_nothing(tmp_path):
    """Tracker.log sends <= 100 params, <= 100 tags and <= 1000 entities per log_batch (MLflow's limits:
    metrics fill the room params and tags leave), and every value arrives."""
    tracker = trk.Tracker(f"sqlite:///{tmp_path / 'mlflow.db'}", "skidbench-x", artifact_root=tmp_path)
    run_id = tracker.start("many", {})
    sent = []
    log_batch = tracker._raw.log_batch
    tracker._raw.log_batch = lambda rid, **kw: sent.append(kw) or log_batch(rid, **kw)
    params, tags = {f"p{i}": i for i in range(150)}, {f"t{i}": i for i in range(30)}
    metrics = {f"m{i}": i / 7 for i in range(1900)}
    tracker.log(run_id, params=params, metrics=metrics, tags=tags)
    sizes = [(len(b["params"]), len(b["tags"]), len(b["metrics"])) for b in sent]
    assert sizes == [(100, 30, 870), (50, 0, 950), (0, 0, 80)]
    tracker.log(run_id, tags={"one": "call"})
    assert len(sent) == 4
    data = MlflowClient(tracker.uri).get_run(run_id).data
    assert data.params == {k: str(v) for k, v in params.items()} and data.metrics == metrics
    want_tags = {**{k: str(v) for k, v in tags.items()}, "one": "call"}
    assert {k: data.tags[k] for k in want_tags} == want_tags


def _statuses(uri: str) -> dict[str, tuple[str, str]]:
    client = MlflowClient(uri)
    exps = [e.experiment_id for e in client.search_experiments()]
    return {r.info.run_name: (r.info.status, r.data.tags.get("skidbench.failure_reason", ""))
            for r in client.search_runs(exps)}  # fmt: skip


def test_ctrl_c_ends_every_open_run_killed_before_the_process_exits(tmp_path):
    """In a tracker's run: a child interrupted while it is being started (before its own handler) ends
    KILLED with its parent, a finished child stays FINISHED, and `skidbench runs` right after lists no run
    RUNNING. Outside one (a stage's handler exits 130 with a run open): the run ends KILLED as the process
    exits, not when a later command reaps it."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = trk.open_tracker(uri, "skidbench-x", artifact_root=tmp_path / "a")
    with pytest.raises(KeyboardInterrupt), tracker.run("evaluate", {}) as parent:
        tracker.end(tracker.start("done", {}, parent))
        tracker.start("starting", {}, parent)
        raise KeyboardInterrupt
    runs = _statuses(uri)
    assert {k: v[0] for k, v in runs.items()} == {
        "evaluate": "KILLED",
        "done": "FINISHED",
        "starting": "KILLED",
    }
    assert runs["starting"][1] == trk.INTERRUPTED
    client = MlflowClient(uri)
    report = bk.runs_report(client, client.search_experiments(), False, bk.STALE_AFTER_S)
    assert report[-1].startswith("0 run(s) RUNNING")

    code = (
        "import sys; from skidbench.benchmark.tracking import store as trk; "
        f"t = trk.open_tracker({uri!r}, 'skidbench-x'); t.start('left open', {{}}); sys.exit(130)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, proc.stderr[-2000:]
    assert _statuses(uri)["left open"] == ("KILLED", bk.EXITED)
