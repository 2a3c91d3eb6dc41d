"""A real local Ray cluster for tests (:func:`skidbench.pipeline.runner.cluster.local_cluster`: ``ray start
--head`` and a worker node on 127.0.0.1, small resources; one per test session, tests/conftest.py
``ray_cluster``) in the tests' environment, and a Hydra callback that kills its own
worker process once, mid-task (fault injection for the Ray sweeps)."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

TESTS = Path(__file__).resolve().parent


#: a lost node is noticed in about three seconds (Ray's default takes tens); six missed health checks, so
#: that a live node starved of CPU for a second on a loaded machine is not taken for dead mid-sweep
FAST_FAILURE = {"health_check_period_ms": 500, "health_check_timeout_ms": 500}
FAST_FAILURE["health_check_failure_threshold"] = 6


@contextlib.contextmanager
def running_ray_cluster() -> Iterator[Any]:
    """A head node and one worker node on 127.0.0.1, one CPU each, whose workers can import this folder
    (see :func:`ray_env`), a lost node noticed in about three seconds; yields it (its ``address``;
    ``add_node``/``kill_node``)."""
    from skidbench.pipeline.runner.cluster import local_cluster

    with local_cluster(num_cpus=1, env=ray_env(), system_config=FAST_FAILURE) as cluster:
        cluster.add_node(num_cpus=1)
        yield cluster


def ray_env(extra: dict | None = None) -> dict[str, str]:
    """Environment of the cluster and of its drivers: this folder importable (the callback below runs on
    the workers), token authentication off (a loopback-only test cluster; Ray would otherwise write a
    token under ~/.ray), no usage reporting."""
    env = dict(os.environ)
    env.pop("SKIDBENCH_OUT", None)  # `make test` exports the project's own: each test sets its out_root
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TESTS), env.get("PYTHONPATH", "")) if p)
    env.update({"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"})
    env.update(extra or {})
    return env


class KillOnce(Callback):
    """``+hydra.callbacks.chaos._target_=ray_cluster.KillOnce +hydra.callbacks.chaos.marker=<file>``: the
    first job (across all processes: the marker is created exclusively) to finish its MLflow run kills
    its own process with SIGKILL just before closing the run, leaving it RUNNING: a worker dying mid-task.
    The marker records ``<pid> <run id>``."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def on_job_start(self, config, **kwargs) -> None:
        from skidbench.benchmark.tracking import store as tracking

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
