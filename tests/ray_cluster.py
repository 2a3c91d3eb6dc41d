"""A real local Ray cluster for tests (``ray start --head --block`` on 127.0.0.1, small resources), and a
Hydra callback that kills its own worker process once, mid-task (fault injection for the Ray sweeps)."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from hydra.experimental.callback import Callback

TESTS = Path(__file__).resolve().parent


def ray_env(extra: dict | None = None) -> dict[str, str]:
    """Environment of the cluster and of its drivers: this folder importable (the callback below runs on
    the workers), token authentication off (a loopback-only test cluster; Ray would otherwise write a
    token under ~/.ray), no usage reporting."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), env.get("PYTHONPATH", "")) if p)
    env.update({"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"})
    env.update(extra or {})
    return env


@contextlib.contextmanager
def running_ray_cluster(num_cpus: int = 2, timeout_s: float = 180.0) -> Iterator[str]:
    """Start a one-node Ray cluster on 127.0.0.1 (``num_cpus`` CPUs, a 100 MB object store, no dashboard)
    in a temporary folder; yield its address (``127.0.0.1:<port>``); stop every process it started."""
    from mlflow_server import free_port

    # Ray's Unix sockets live under the temp dir: keep its path short (pytest's tmp_path is too long)
    tmp = Path(tempfile.mkdtemp(prefix="skbray-"))
    port = free_port()
    cmd = [
        str(Path(sys.executable).with_name("ray")), "start", "--head", "--block",
        "--node-ip-address=127.0.0.1", f"--port={port}", f"--num-cpus={num_cpus}",
        "--object-store-memory=100000000", "--include-dashboard=false", "--disable-usage-stats",
        f"--ray-client-server-port={free_port()}", f"--dashboard-agent-listen-port={free_port()}",
        f"--temp-dir={tmp}",
    ]  # fmt: skip
    log_path = tmp / "ray-start.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=ray_env(), start_new_session=True, cwd=tmp
        )
    try:
        deadline = time.monotonic() + timeout_s
        while b"Ray runtime started" not in log_path.read_bytes():
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"ray start failed: {log_path.read_text()[-3000:]}")
            time.sleep(0.5)
        yield f"127.0.0.1:{port}"
    finally:
        # every process of the cluster (GCS, raylet, agents, workers) is in the process group of
        # `ray start`: terminate the group, then kill what is left of it after a grace period
        for sig, grace_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, sig)
            deadline = time.monotonic() + grace_s
            while time.monotonic() < deadline and _group_alive(proc.pid):
                proc.poll()  # reap `ray start` itself
                time.sleep(0.2)
        proc.wait(timeout=10)
        shutil.rmtree(tmp, ignore_errors=True)


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` other than a zombie is still running."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":  # fields: state, ppid, pgrp, ...
            return True
    return False


class KillOnce(Callback):
    """``+hydra.callbacks.chaos._target_=ray_cluster.KillOnce +hydra.callbacks.chaos.marker=<file>``: the
    first job (across all processes: the marker is created exclusively) to finish its MLflow run kills
    its own process with SIGKILL just before closing the run, leaving it RUNNING: a worker dying mid-task.
    The marker records ``<pid> <run id>``."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def on_job_start(self, config, **kwargs) -> None:
        from skidbench.benchmark import tracking

        original = tracking.Tracker.end
        if getattr(original, "chaos", False):
            return
        marker = self.marker

        def end(tracker, run_id: str, status: str = "FINISHED") -> None:
            if status == "FINISHED":
                try:
                    fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    pass
                else:
                    os.write(fd, f"{os.getpid()} {run_id}".encode())
                    os.close(fd)
                    os.kill(os.getpid(), signal.SIGKILL)
            return original(tracker, run_id, status)

        end.chaos = True  # type: ignore[attr-defined]
        tracking.Tracker.end = end  # type: ignore[method-assign]
