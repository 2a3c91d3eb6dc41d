"""What an MLflow run is and who made it: the tags every run carries, its name and description, its
config as params. No MLflow calls here (the store: :mod:`skidbench.benchmark.tracking.store`; the software a
run ran, versions and commit: :mod:`skidbench.pipeline.runner.environment`).

Who made a run (a lab shares one tracking server): ``mlflow.user`` (MLflow's own "Created by" column;
``SKIDBENCH_USER`` when set, else the login name), ``skidbench.host``, ``skidbench.out_root`` (the output
root the run's files went to) and ``skidbench.session`` (one id per process: every run one command
opened). ``compare`` reads a user's own runs by ``mlflow.user``; the process tags (host, boot id, pid)
and the heartbeat tell a run left open by a process that is gone
(:mod:`skidbench.benchmark.tracking.bookkeeping`).
"""

from __future__ import annotations

import datetime as dt
import functools
import getpass
import os
import shlex
import socket
import sys
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from skidbench.pipeline.runner.environment import git_commit

__all__ = [
    "MAX_PARAM_LEN",
    "MAX_TAG_LEN",
    "TAG_ROLE",
    "TAG_MODEL",
    "TAG_MODEL_VERSION",
    "TAG_PLUGIN",
    "TAG_TERRAIN",
    "TAG_DATASET",
    "TAG_FINGERPRINT",
    "TAG_DATASET_ID",
    "TAG_GIT",
    "TAG_STATUS",
    "TAG_REASON",
    "TAG_PARENT",
    "TAG_USER",
    "TAG_HOST",
    "TAG_BOOT",
    "TAG_PID",
    "TAG_OUT_ROOT",
    "TAG_SESSION",
    "TAG_HEARTBEAT",
    "TAG_RUN_KEY",
    "TAG_INPUTS",
    "TAG_EXTERNAL",
    "TAG_PREDICTIONS_SHA256",
    "TAG_SUBMISSION",
    "TAG_NOTE",
    "TAG_EXPERIMENT_KIND",
    "EXPERIMENT_KIND",
    "experiment_tags",
    "USER_ENV",
    "current_user",
    "session_id",
    "process_tags",
    "owner_tags",
    "utc_now",
    "parse_utc",
    "flatten",
    "source_tags",
    "task_overrides",
    "reproduce_command",
    "describe",
    "parent_run_name",
    "config_params",
    "git_commit",
]

MAX_PARAM_LEN = 6000  # MLflow's limit on a param value
MAX_TAG_LEN = 5000

TAG_ROLE = "skidbench.role"
TAG_MODEL = "skidbench.model"
TAG_MODEL_VERSION = "skidbench.model_version"
TAG_PLUGIN = "skidbench.plugin_package"
TAG_TERRAIN = "skidbench.terrain"
TAG_DATASET = "skidbench.dataset"
TAG_FINGERPRINT = "skidbench.dataset_fingerprint"  # content of the split files a run read
TAG_DATASET_ID = (
    "skidbench.dataset_id"  # the dataset's identity (pipeline/datasets/identity.py): runs never mix
)
TAG_GIT = "skidbench.git_commit"
TAG_STATUS = "skidbench.status"
TAG_REASON = "skidbench.failure_reason"
TAG_PARENT = "mlflow.parentRunId"
TAG_USER = "mlflow.user"  # who made the run (the UI's "Created by")
TAG_HOST = "skidbench.host"
TAG_BOOT = "skidbench.boot_id"
TAG_PID = "skidbench.pid"
TAG_OUT_ROOT = "skidbench.out_root"  # the output root the run's files went to
TAG_SESSION = "skidbench.session"  # one id per process: the runs one command opened
TAG_HEARTBEAT = "skidbench.heartbeat"  # UTC time a live process last said its open run is alive
TAG_RUN_KEY = "skidbench.run_key"
TAG_INPUTS = "skidbench.inputs"  # the input protocol (commanded | response | measured)
TAG_EXTERNAL = "skidbench.external"  # "true" on a run of `skidbench score` (benchmark/release/score.py)
TAG_PREDICTIONS_SHA256 = "skidbench.predictions_sha256"  # the sha256 of the predictions file it scored
#: + link, submitter, submitted (its date), description: a submission's identity (benchmark/release/)
TAG_SUBMISSION = "skidbench.submission."
TAG_NOTE = "mlflow.note.content"  # a run's (or an experiment's) description, Markdown, shown by the UI
TAG_EXPERIMENT_KIND = "mlflow.experimentKind"  # which default page the MLflow 3 UI opens an experiment on
EXPERIMENT_KIND = "custom_model_development"  # its runs table (unset: the GenAI overview of traces)
#: who runs skidbench, when the login name does not say it (a lab's shared account)
USER_ENV = "SKIDBENCH_USER"


def experiment_tags(name: str) -> dict[str, str]:
    """The tags of a skidbench experiment: its kind (the UI opens it on its runs table, not on the GenAI
    overview) and a description."""
    return {
        TAG_EXPERIMENT_KIND: EXPERIMENT_KIND,
        TAG_NOTE: f"skidbench benchmark runs of `{name.removeprefix('skidbench-')}`: one parent run per "
        "`skidbench evaluate` (its name: dataset, input protocol, user@host, start time) with a child run "
        "per model and terrain (fitted on Train, scored on the CV and LD test splits; metrics "
        "`<split>_<horizon>_<trans|rot>_rmsre_pct` are RMSRE in %, lower is better), and one run per "
        "`skidbench calibrate`. `skidbench compare` prints the link of a saved view that shows them.",
    }


@functools.cache
def _boot_id() -> str:
    """This machine's boot id (Linux), which tells two machines of one host name apart; '' elsewhere."""
    try:
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return ""


def current_user() -> str:
    """Who runs this process: ``SKIDBENCH_USER`` when set, else the login name (``getpass.getuser``)."""
    user = os.environ.get(USER_ENV, "").strip()
    if user:
        return user
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "unknown"


@functools.cache
def session_id() -> str:
    """This process's session id (12 hex digits): the same on every run it opens."""
    return uuid.uuid4().hex[:12]


def process_tags() -> dict[str, str]:
    """The tags that name the process starting a run: host, boot id, pid and session."""
    return {
        TAG_HOST: socket.gethostname(),
        TAG_BOOT: _boot_id(),
        TAG_PID: str(os.getpid()),
        TAG_SESSION: session_id(),
    }


def owner_tags(out_root: str | Path | None = None) -> dict[str, str]:
    """Who made a run and where its files went: user, the process tags and the output root."""
    tags = {TAG_USER: current_user(), **process_tags()}
    if out_root:
        tags[TAG_OUT_ROOT] = str(Path(out_root).absolute())
    return tags


def utc_now() -> str:
    """The current UTC time as a heartbeat tag holds it (``2026-11-25T10:00:00Z``)."""
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def parse_utc(value: str | None) -> float | None:
    """Seconds since the epoch of a :func:`utc_now` string, or None when it is not one."""
    try:
        return dt.datetime.strptime(str(value), "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=dt.UTC).timestamp()
    except ValueError:
        return None


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Flatten a nested mapping to ``a.b.c`` -> str(value) (lists as their repr), for MLflow params."""
    out: dict[str, str] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            s = "null" if v is None else str(v)
            out[key] = s if len(s) <= MAX_PARAM_LEN else s[: MAX_PARAM_LEN - 3] + "..."
    return out


def source_tags() -> dict[str, str]:
    """MLflow's own tags for who started a run and from what (the UI's "Created by" and "Source"):
    ``mlflow.user`` (:func:`current_user`), ``mlflow.source.type`` LOCAL, ``mlflow.source.name`` the
    command line, the git commit of the skidbench tree."""
    prog = Path(sys.argv[0]).name if sys.argv and sys.argv[0] else "python"  # e.g. "skidbench evaluate"
    tags = {
        TAG_USER: current_user(),
        "mlflow.source.type": "LOCAL",
        "mlflow.source.name": " ".join([prog, shlex.join(sys.argv[1:])]).strip()[:MAX_TAG_LEN],
    }
    commit = git_commit()
    if commit != "unknown":
        tags["mlflow.source.git.commit"] = commit.split("+")[0]
    return tags


def task_overrides() -> list[str]:
    """The command-line overrides of the running Hydra app ([] outside one)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return [str(o) for o in HydraConfig.get().overrides.task]
    except (ImportError, ValueError):
        return []


def reproduce_command(stage: str, extra: Sequence[str] = (), drop: Sequence[str] = ()) -> str:
    """``skidbench <stage> <this run's overrides> <extra>``; overrides of the keys ``drop`` (and of the keys
    ``extra`` sets) are left out so that the command runs as printed."""
    extra = list(extra)
    keys = {o.split("=", 1)[0].lstrip("+~") for o in extra} | set(drop)
    kept = [o for o in task_overrides() if o.split("=", 1)[0].lstrip("+~") not in keys]
    return shlex.join(["skidbench", stage, *kept, *extra])


def describe(title: str, facts: Mapping[str, Any], command: str) -> str:
    """A run description (the ``mlflow.note.content`` tag; Markdown): a title line, facts, the command."""
    lines = [title, ""]
    lines += [f"- **{k}**: {v}" for k, v in facts.items() if v not in (None, "")]
    lines += ["", "Reproduce:", "", "```", command, "```", ""]
    return "\n".join(lines)[:MAX_TAG_LEN]


def parent_run_name(stage: str, dataset: str, inputs: str, when: dt.datetime | None = None) -> str:
    """``evaluate sim-mini commanded alice@lab-pc 2026-11-23 23:10:05``: stage, dataset, input protocol,
    who and on which host, UTC start time (to the second; a parent run's name is unique and says what it
    is and whose)."""
    when = when or dt.datetime.now(dt.UTC)
    host = socket.gethostname().split(".")[0]
    return f"{stage} {dataset} {inputs} {current_user()}@{host} {when:%Y-%m-%d %H:%M:%S}"


def config_params(conf: Mapping[str, Any], model: Mapping[str, Any] | None = None) -> dict[str, str]:
    """A run's config as params: the stage config without any ``model`` node (a ``+model=...`` override
    belongs to one model only), plus ``model.*`` of ``model`` (``{"name", "params", "options"}``: the
    config of the run's own model, :func:`skidbench.models.fitting.fit.model_config`) when given."""
    conf = {k: v for k, v in conf.items() if k != "model"}
    if model is not None:
        conf["model"] = {"name": model.get("name"), "params": model.get("params") or {},
                         "options": model.get("options") or {}}  # fmt: skip
    return flatten(conf)
