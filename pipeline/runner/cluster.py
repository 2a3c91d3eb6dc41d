"""Ray: a Hydra sweep's jobs, and a data stage's items, as Ray tasks on a Ray cluster (the one home for
Ray in skidbench).

``skidbench <stage> -m <sweep> hydra/launcher=ray`` (``conf/hydra/launcher/ray.yaml``; the launcher class
is the thin plugin ``hydra_plugins/skidbench_ray_launcher``) runs every job of the sweep as one Ray task:

- **where**: ``hydra.launcher.address``: null starts a private local Ray instance for the sweep and stops
  it at the end (unless ``RAY_ADDRESS`` is set, Ray's own variable, which is then used); ``auto`` joins
  the cluster this machine is part of (``ray start``); ``ray://<head>:10001`` connects through Ray Client;
  ``<head>:6379`` connects a node of the cluster to its head directly. A ``host:port`` address is first
  checked with a TCP connection (``connect_timeout_s``), so an unreachable cluster is one line at once
  rather than Ray's 30 s of retries and a traceback.
- **retries**: a job whose worker process or node dies is re-run by Ray (``max_retries``). Jobs key their
  MLflow runs (``skidbench.run_key``, :func:`skidbench.benchmark.tracking.sweep.run_key`): a retried job
  closes the
  run its dead attempt left open as KILLED, and logs nothing if that attempt had finished. So a sweep of
  N jobs yields N finished runs, each once.
- **environment**: the driver's environment variables that start with one of ``forward_env`` (the
  MLflow server ``MLFLOW_TRACKING_URI`` and its credentials, ``SKIDBENCH_OUT``) are set in every job, and
  a job runs in the driver's working directory when that exists on its node; on a cluster of several
  machines ``out_root`` must be a folder every node sees (the splits are read from it, fits written to it).

A data stage run with ``hydra/launcher=ray`` (no ``-m``) maps its items (a bag, a sequence, a terrain) to
Ray tasks through :func:`map_items` (``pipeline/runner/tasks.py`` chooses it over the forked workers):
the same address and environment, one retry of a failed item, each task writing its own outputs.

Ray is optional (``pip install 'skidbench[cluster]'``); it is imported only when a run uses it.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.errors import ClusterError, one_line

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'skidbench[cluster]' (Ray with its client)"


@dataclass
class RaySettings:
    """``hydra.launcher`` of ``conf/hydra/launcher/ray.yaml`` (see there for each key)."""

    address: str | None = None
    connect_timeout_s: float = 10.0
    num_cpus_per_job: float = 1.0
    max_retries: int = 3
    forward_env: Sequence[str] = ("MLFLOW_", "SKIDBENCH_")
    local: Mapping[str, Any] = field(default_factory=dict)


def import_ray():
    try:
        import ray
    except ImportError as exc:
        raise ClusterError(f"hydra/launcher=ray needs Ray, not installed ({exc}); {INSTALL_HINT}") from None
    return ray


def _host_port(address: str) -> tuple[str, int] | None:
    """``ray://host:port`` or ``host:port`` -> (host, port); None for ``auto``/``local``."""
    rest = address[len("ray://") :] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)


def check_reachable(address: str, timeout_s: float) -> None:
    """Raise ClusterError (one line) when ``address``'s host:port does not accept a TCP connection."""
    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=timeout_s):
            pass
    except OSError as exc:
        reason = f"no answer in {timeout_s:g} s" if isinstance(exc, TimeoutError) else exc.strerror
        raise ClusterError(
            f"cannot reach the Ray cluster at {address} ({reason or type(exc).__name__}); start it "
            "(ray start --head) or set hydra.launcher.address (auto, ray://<head>:10001, <head>:6379)"
        ) from None


def resolve_address(address: str | None) -> str:
    """The address to connect to: the configured one, else ``RAY_ADDRESS``, else ``local`` (a new local
    instance; never another user's cluster that happens to run on this machine)."""
    if address not in (None, "", "null"):
        return str(address)
    return os.environ.get("RAY_ADDRESS") or "local"


def connect(settings: RaySettings) -> tuple[Any, bool]:
    """``ray.init`` for a sweep; returns (ray, whether this call started a local instance)."""
    ray = import_ray()
    address = resolve_address(settings.address)
    if ray.is_initialized():
        return ray, False
    check_reachable(address, settings.connect_timeout_s)
    kwargs: dict[str, Any] = {"address": address, "logging_level": logging.WARNING, "log_to_driver": True}
    local = address == "local"
    if local:
        kwargs.update({k: v for k, v in dict(settings.local).items() if v is not None})
        kwargs.setdefault("include_dashboard", False)
    started = time.perf_counter()
    try:
        with warnings.catch_warnings():  # Ray Client's timeout warning: the error below says it in one line
            warnings.simplefilter("ignore", UserWarning)
            ray.init(**kwargs)
    except Exception as exc:  # ConnectionError, a bad address, a version mismatch, ...
        raise ClusterError(f"cannot reach the Ray cluster at {address} ({type(exc).__name__}: "
                           f"{one_line(str(exc))[:300]})") from None  # fmt: skip
    log.info(
        "Ray: %s in %.1f s (%s CPUs)",
        "started a local instance" if local else f"connected to {address}",
        time.perf_counter() - started,
        ray.cluster_resources().get("CPU", "?"),
    )
    return ray, local


def forwarded_env(prefixes: Sequence[str], environ: Mapping[str, str] | None = None) -> dict[str, str]:
    """The driver's environment variables whose names start with one of ``prefixes``."""
    env = os.environ if environ is None else environ
    return {k: v for k, v in env.items() if any(k.startswith(p) for p in prefixes)}


# -- the task (runs on a Ray worker) ---------------------------------------------------------------
def execute_job(
    hydra_context: Any,
    sweep_config: Any,
    task_function: Any,
    singleton_state: dict[Any, Any],
    env: Mapping[str, str],
    cwd: str,
) -> Any:
    """One Hydra job on a Ray worker: Hydra's ``run_job`` with the driver's environment and working
    directory. A stage's one-line error (``SystemExit``) comes back as ``("exit", code)``."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.singleton import Singleton
    from hydra.core.utils import run_job, setup_globals

    os.environ.update(env)
    if cwd and Path(cwd).is_dir():
        os.chdir(cwd)
    setup_globals()
    Singleton.set_state(singleton_state)
    HydraConfig.instance().set_config(sweep_config)
    try:
        return run_job(
            hydra_context=hydra_context,
            task_function=task_function,
            config=sweep_config,
            job_dir_key="hydra.sweep.dir",
            job_subdir_key="hydra.sweep.subdir",
        )
    except SystemExit as exc:  # the stage printed its error (forwarded to the driver's stderr)
        return ("exit", exc.code)


# -- the driver ------------------------------------------------------------------------------------
def launch(
    settings: RaySettings,
    hydra_context: Any,
    task_function: Any,
    config: Any,
    job_overrides: Sequence[Sequence[str]],
    initial_job_idx: int,
) -> list[Any]:
    """Run the jobs as Ray tasks; their ``JobReturn`` in order. A job that failed outright (the stage's
    one-line error, or lost after ``max_retries``) is a :class:`ClusterError` naming every such job."""
    from hydra.core.singleton import Singleton
    from hydra.core.utils import JobReturn, configure_log, filter_overrides, setup_globals
    from omegaconf import open_dict

    setup_globals()
    configure_log(config.hydra.hydra_logging, config.hydra.verbose)
    sweep_dir = Path(str(config.hydra.sweep.dir))
    sweep_dir.mkdir(parents=True, exist_ok=True)
    ray, started_local = connect(settings)
    refs: list[Any] = []
    try:
        remote = ray.remote(execute_job)
        options = {"num_cpus": settings.num_cpus_per_job, "max_retries": int(settings.max_retries)}
        env = forwarded_env(settings.forward_env)
        log.info("Ray: launching %d jobs (%g CPU each, up to %d retries), sweep output dir %s",
                 len(job_overrides), settings.num_cpus_per_job, settings.max_retries, sweep_dir)  # fmt: skip
        state = Singleton.get_state()
        names: list[str] = []
        for k, overrides in enumerate(job_overrides):
            idx = initial_job_idx + k
            name = " ".join(filter_overrides(overrides))
            log.info("\t#%d : %s", idx, name)
            sweep_config = hydra_context.config_loader.load_sweep_config(config, list(overrides))
            with open_dict(sweep_config):
                sweep_config.hydra.job.id = f"{sweep_config.hydra.job.name}_{idx}"
                sweep_config.hydra.job.num = idx
            ref = remote.options(name=f"skidbench job {idx}", **options).remote(
                hydra_context, sweep_config, task_function, state, env, os.getcwd()
            )
            refs.append(ref)
            names.append(f"#{idx} ({name})")
        results = _gather(ray, refs, names)
    except KeyboardInterrupt:
        for ref in refs:
            ray.cancel(ref, force=True)
        raise
    finally:
        ray.shutdown()  # a local instance this sweep started stops with it
        if started_local:
            log.info("Ray: local instance stopped")
    failed = [f"{n}: {r}" for n, r in zip(names, results, strict=True) if not isinstance(r, JobReturn)]
    if failed:
        raise ClusterError(f"{len(failed)} of {len(results)} jobs failed: " + "; ".join(failed))
    return results


def _gather(ray: Any, refs: list[Any], names: list[str]) -> list[Any]:
    """Every job's JobReturn (or why it failed, as a string), logging each as it ends."""
    from ray.exceptions import RayError

    out: dict[Any, Any] = {}
    pending = list(refs)
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        ref = ready[0]
        try:
            res = ray.get(ref)
            if isinstance(res, tuple) and res[:1] == ("exit",):
                res = f"exit status {res[1]} (its error is printed above)"
        except RayError as exc:  # lost after max_retries, cancelled, ...
            res = f"{type(exc).__name__}: {one_line(str(exc))[:300]}"
        out[ref] = res
        what = "failed" if isinstance(res, str) else "done"
        log.info("Ray: job %s %s (%d/%d)", names[refs.index(ref)], what, len(out), len(refs))
    return [out[r] for r in refs]


# -- a stage's items as Ray tasks (the data stages: one task per sequence or terrain) ---------------
def run_item(fn: Any, args: tuple, env: Mapping[str, str], cwd: str) -> Any:
    """One item of a stage on a Ray worker: ``fn(*args)`` with the driver's forwarded environment and
    working directory, both restored afterwards (a worker runs the next task in the state it found)."""
    saved_env, saved_cwd = dict(os.environ), os.getcwd()
    os.environ.update(env)
    if cwd and Path(cwd).is_dir():
        os.chdir(cwd)
    try:
        return fn(*args)
    finally:
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)


def map_items(
    settings: RaySettings,
    fn: Any,
    calls: Sequence[tuple],
    names: Sequence[str],
    done: Any = None,
    what: str = "task",
) -> list[Any]:
    """``[fn(*args) for args in calls]`` as Ray tasks, one per call, spread over the cluster's nodes, each
    holding ``num_cpus_per_job`` CPUs; ``done(i, result)`` runs here as each finishes. A task that fails
    (its exception, or its worker process or node lost) is run once more; a second failure cancels the
    tasks not finished and raises: the task's own :class:`SkidbenchError` as it was (its message names
    the file), anything else as a :class:`ClusterError` naming ``names[i]``. The tasks write their outputs
    themselves (under an ``out_root`` every node sees) and return what the driver needs to know of them."""
    from ray.exceptions import RayError, RayTaskError

    from skidbench.pipeline.core.errors import SkidbenchError

    ray, started_local = connect(settings)
    refs: list[Any] = []
    try:
        remote = ray.remote(run_item)
        options = {"num_cpus": settings.num_cpus_per_job, "max_retries": 1, "retry_exceptions": True,
                   "scheduling_strategy": "SPREAD"}  # fmt: skip
        env, cwd = forwarded_env(settings.forward_env), os.getcwd()
        fn_ref = ray.put(fn)
        for args, name in zip(calls, names, strict=True):
            task = remote.options(name=f"skidbench {what} {name}", **options)
            refs.append(task.remote(fn_ref, args, env, cwd))
        index = {ref: i for i, ref in enumerate(refs)}
        results: list[Any] = [None] * len(refs)
        pending = list(refs)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            i = index[ready[0]]
            try:
                results[i] = ray.get(ready[0])
            except RayTaskError as exc:
                cause = exc.cause if isinstance(getattr(exc, "cause", None), BaseException) else None
                if isinstance(cause, SkidbenchError):
                    raise cause from None
                why = one_line(str(cause if cause else exc))[:300]
                why = f"{type(cause).__name__}: {why}" if cause else why
                raise ClusterError(f"{what} {names[i]} failed twice on the Ray cluster ({why})") from None
            except RayError as exc:  # its worker process or node lost twice, or cancelled
                raise ClusterError(
                    f"{what} {names[i]} failed twice on the Ray cluster ({type(exc).__name__}: "
                    f"{one_line(str(exc))[:300]})"
                ) from None
            if done is not None:
                done(i, results[i])
        return results
    except BaseException:
        for ref in refs:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise
    finally:
        if started_local:
            ray.shutdown()


# -- a throwaway local cluster ---------------------------------------------------------------------
@dataclass
class LocalCluster:
    address: str  # 127.0.0.1:<port>, for hydra.launcher.address
    pgid: int  # the process group of the head node's processes (``ray start --head``)
    env: Mapping[str, str] | None = None  # the environment the nodes start in
    tmp: Path | None = None  # the cluster's temporary folder (logs, sockets)
    nodes: list[subprocess.Popen] = field(default_factory=list)  # the worker nodes added, still running

    def cpu_ticks(self) -> dict[tuple[int, int], int]:
        """(pid, start time) -> utime + stime in clock ticks of every live process of the cluster: the
        whole process tree of each node's ``ray start`` (workers run in process groups of their own;
        Linux)."""
        roots = [self.pgid, *(p.pid for p in self.nodes)]
        return {(pid, int(f[19])): int(f[11]) + int(f[12]) for r in roots for pid, f in _tree_stats(r)}

    def add_node(self, num_cpus: int = 1, object_store_mb: int = 100, env: Mapping[str, str] | None = None,
                 timeout_s: float = 180.0) -> subprocess.Popen:  # fmt: skip
        """Start a worker node (``ray start --address``, a raylet of its own on 127.0.0.1 with ``num_cpus``
        CPUs) in the cluster's environment updated by ``env``; returns its ``ray start`` process."""
        cmd = [
            str(Path(sys.executable).with_name("ray")), "start", f"--address={self.address}", "--block",
            "--node-ip-address=127.0.0.1", f"--num-cpus={num_cpus}",
            f"--object-store-memory={object_store_mb * 1_000_000}", "--disable-usage-stats",
            f"--dashboard-agent-listen-port={_free_port()}", f"--metrics-export-port={_free_port()}",
        ]  # fmt: skip
        environ = {**(os.environ if self.env is None else self.env), **(env or {})}
        proc = _start_node(cmd, environ, self.tmp or Path(tempfile.gettempdir()), timeout_s)
        self.nodes.append(proc)
        return proc

    def kill_node(self, node: subprocess.Popen) -> None:
        """SIGKILL every process of a worker node at once (its raylet, agents and workers, stopped ones
        too): a machine of the cluster lost."""
        for pid, _ in list(_tree_stats(node.pid)):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        node.wait(timeout=30)
        self.nodes.remove(node)


def _start_node(cmd: list[str], environ: Mapping[str, str], tmp: Path, timeout_s: float) -> subprocess.Popen:
    """``cmd`` (a blocking ``ray start``) in a session of its own, once it says the node started."""
    log_path = Path(tempfile.mkstemp(prefix="ray-start-", suffix=".log", dir=tmp)[1])
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(environ), start_new_session=True, cwd=tmp
        )
    deadline = time.monotonic() + timeout_s
    while b"Ray runtime started" not in log_path.read_bytes():
        if proc.poll() is not None or time.monotonic() > deadline:
            _stop_group(proc)
            tail = one_line(log_path.read_text()[-500:])
            raise ClusterError(f"{' '.join(cmd[1:3])} did not start a Ray node: {tail}")
        time.sleep(0.5)
    return proc


def _stop_group(proc: subprocess.Popen) -> None:
    """Terminate the process group of ``proc`` (a node's ``ray start``: its GCS, raylet, agents), then
    kill what is left of it after a grace period."""
    for sig, grace_s in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        deadline = time.monotonic() + grace_s
        while time.monotonic() < deadline and _group_alive(proc.pid):
            proc.poll()  # reap `ray start` itself
            time.sleep(0.2)
    proc.wait(timeout=10)


@contextlib.contextmanager
def local_cluster(
    num_cpus: int = 2,
    object_store_mb: int = 100,
    env: Mapping[str, str] | None = None,
    timeout_s: float = 180.0,
    system_config: Mapping[str, Any] | None = None,
) -> Iterator[LocalCluster]:
    """A throwaway Ray cluster on 127.0.0.1 (tests, ``make bench``): ``ray start --head`` with
    ``num_cpus`` CPUs, an ``object_store_mb`` object store, no dashboard, in a temporary folder and the
    environment ``env`` (``system_config``: Ray's internal settings, e.g. how fast a lost node is
    noticed); yields it (its address; :meth:`LocalCluster.add_node` adds worker nodes) and stops every
    process it started (never ``ray stop``, which stops every Ray process of the user)."""
    # Ray's Unix sockets live under the temp dir: keep its path short (pytest's tmp_path is too long)
    tmp = Path(tempfile.mkdtemp(prefix="skbray-"))
    port = _free_port()
    cmd = [
        str(Path(sys.executable).with_name("ray")), "start", "--head", "--block",
        "--node-ip-address=127.0.0.1", f"--port={port}", f"--num-cpus={num_cpus}",
        f"--object-store-memory={object_store_mb * 1_000_000}", "--include-dashboard=false",
        "--disable-usage-stats",
        f"--ray-client-server-port={_free_port()}", f"--dashboard-agent-listen-port={_free_port()}",
        f"--temp-dir={tmp}",
    ]  # fmt: skip
    if system_config:
        cmd.append(f"--system-config={json.dumps(dict(system_config))}")
    environ = dict(os.environ if env is None else env)
    head = _start_node(cmd, environ, tmp, timeout_s)
    cluster = LocalCluster(f"127.0.0.1:{port}", head.pid, environ, tmp)
    try:
        yield cluster
    finally:
        # every process of a node (GCS, raylet, agents; workers exit with their raylet) is in the process
        # group of its `ray start`: the worker nodes first, then the head
        for node in [*cluster.nodes, head]:
            _stop_group(node)
        shutil.rmtree(tmp, ignore_errors=True)


def _proc_stats() -> Iterator[tuple[int, list[str]]]:
    """(pid, the ``/proc/<pid>/stat`` fields after the command name: state, ppid, pgrp, ...)."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            yield int(stat.parent.name), stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError, ValueError):
            continue


def _group_alive(pgid: int) -> bool:
    """Whether a process of group ``pgid`` other than a zombie is still running."""
    return any(int(f[2]) == pgid and f[0] != "Z" for _, f in _proc_stats())


def _tree_stats(root: int) -> Iterator[tuple[int, list[str]]]:
    """The ``/proc`` stat fields of process ``root`` and of all its descendants."""
    stats = dict(_proc_stats())
    children: dict[int, list[int]] = {}
    for pid, f in stats.items():
        children.setdefault(int(f[1]), []).append(pid)
    todo = [root]
    while todo:
        pid = todo.pop()
        if pid in stats:
            yield pid, stats[pid]
        todo.extend(children.get(pid, []))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
