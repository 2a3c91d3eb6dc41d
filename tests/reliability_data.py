"""A micro simulated dataset (3 tile sequences of 8 s, no images, no loops) built once per session by the
CLI, and helpers for the reliability tests (subprocess runs, snapshots of an output root)."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

SCALE = ["scale=tiny", "scale.name=micro"]
SIMULATE = [
    *SCALE,
    "images=false",
    *(f"scale.simulate.durations.{c}.tile=8" for c in ("train", "cv", "ld")),
    *(f"scale.simulate.durations.{c}.{t}=0" for c in ("train", "cv", "ld") for t in ("asphalt", "grass")),
    *(f"scale.simulate.loops.{t}=0" for t in ("tile", "asphalt", "grass")),
]
DATASET = "sim-micro"
#: ``SKIDBENCH_FAULT=<action>@<n>[:<substring>]`` kills or fails a run at a write (tests/fault_injection)
FAULT_ENV = "SKIDBENCH_FAULT"
FAULT_INJECTION = Path(__file__).resolve().parent / "fault_injection"
#: stage -> overrides of a run of the micro dataset
STAGE_ARGS = {
    "simulate": SIMULATE,
    "extract": [*SCALE, "extract.progress=false"],
    "groundtruth": [*SCALE, "groundtruth.method=pose_topic"],
    "split": SCALE,
    # calibrate.use=false: these runs are about faults and reruns, not the calibration (which only
    # `skidbench calibrate` computes; PIPELINE does not run it)
    "fit": [*SCALE, "model=edd", "terrain=tile", "track=false", "calibrate.use=false"],
    # horizons=[6.0]: the board's horizon only (these runs are about faults, reruns and the store; five
    # horizons also make every compare rank each horizon's aggressiveness strata)
    "evaluate": [*SCALE, "models=[ideal,edd]", "log_figures=false", "calibrate.use=false", "horizons=[6.0]"],
}
PIPELINE = ("simulate", "extract", "groundtruth", "split")


def skidbench(
    stage: str,
    out_root: Path,
    *extra: str,
    env: dict | None = None,
    check: bool = True,
    base: list[str] | None = None,
    here: bool = False,
):
    """``skidbench <stage>`` on the micro dataset in a subprocess (niced: the tests share 2 cores);
    ``base`` replaces the stage's default overrides (``STAGE_ARGS``). ``here``: in this process
    (:func:`in_process`), for a run whose process is not what is tested (not killed, interrupted or
    given an environment of its own)."""
    e = {**os.environ, "SKIDBENCH_OUT": str(out_root), "PYTHONHASHSEED": "0", **(env or {})}
    if e.get(FAULT_ENV):  # the fault hook (tests/fault_injection), loaded at start-up by its sitecustomize
        e["PYTHONPATH"] = os.pathsep.join(filter(None, [str(FAULT_INJECTION), e.get("PYTHONPATH")]))
    if "MLFLOW_TRACKING_URI" not in (env or {}):
        e.pop("MLFLOW_TRACKING_URI", None)
    args = STAGE_ARGS.get(stage, SCALE) if base is None else base
    if here:
        assert not env, "a run given an environment of its own needs a process of its own"
        proc = in_process([stage, *args, *extra], e)
    else:
        cmd = [sys.executable, "-m", "skidbench.pipeline.cli.main", stage, *args, *extra]
        proc = subprocess.run(
            ["nice", "-n", "5", *cmd],
            env=e,
            capture_output=True,
            text=True,
            timeout=600,
            start_new_session=True,
        )
    if check and proc.returncode != 0:
        raise AssertionError(f"skidbench {stage} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return proc


def in_process(argv: list[str], env: dict[str, str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``skidbench <argv>`` run by the console script's ``main`` in this process, in the environment ``env``
    and the folder ``cwd``: what a subprocess runs after Python's start-up, without the seconds of imports
    each command's process pays (MLflow's store alone: 3-6 CPU-s). Returns what :func:`subprocess.run`
    would: the exit status (``SystemExit``'s; 1 and the traceback on stderr for an uncaught exception),
    stdout and stderr. They are files (``sys.stdout``/``sys.stderr`` for the call, appended to): what a
    stage's forked workers print lands there too, as it would in a process of its own. The environment,
    the folder, ``sys.argv`` and the root logger's handlers are restored afterwards."""
    import logging
    import tempfile
    import traceback

    from skidbench.pipeline.cli.main import main

    saved_env, saved_argv, saved_cwd = dict(os.environ), sys.argv[:], os.getcwd()
    saved_streams = sys.stdout, sys.stderr
    root = logging.getLogger()
    saved_handlers, saved_level = root.handlers[:], root.level
    code: int = 0
    with tempfile.TemporaryDirectory(prefix="skidbench-cli-") as tmp:
        out_path, err_path = Path(tmp) / "stdout", Path(tmp) / "stderr"
        streams = [open(p, "a", buffering=1) for p in (out_path, err_path)]  # line-buffered, O_APPEND
        try:
            os.environ.clear()
            os.environ.update(env)
            if cwd is not None:
                os.chdir(cwd)
            sys.stdout, sys.stderr = streams
            try:
                main(list(argv))
            except SystemExit as exc:  # as the interpreter turns it into the process's exit status
                if isinstance(exc.code, int) or exc.code is None:
                    code = exc.code or 0
                else:
                    print(exc.code, file=sys.stderr)
                    code = 1
            except Exception:  # noqa: BLE001 - a process prints it and exits 1
                traceback.print_exc()
                code = 1
        finally:
            sys.stdout, sys.stderr = saved_streams
            for f in streams:
                f.close()
            for h in root.handlers[:]:  # the run's handlers (Hydra's job logging: its console and log file)
                if h not in saved_handlers:
                    root.removeHandler(h)
                    h.close()
            for h in saved_handlers:
                if h not in root.handlers:
                    root.addHandler(h)
            root.setLevel(saved_level)
            os.chdir(saved_cwd)
            os.environ.clear()
            os.environ.update(saved_env)
            sys.argv = saved_argv
        stdout, stderr = out_path.read_text(), err_path.read_text()
    return subprocess.CompletedProcess(["skidbench", *argv], code, stdout, stderr)


def copy_splits(micro_root: Path, root: Path) -> None:
    """The micro dataset's split files and its manifest (which lists them) into another output root."""
    import shutil

    shutil.copytree(micro_root / DATASET / "splits", root / DATASET / "splits")
    (root / DATASET / "raw").mkdir(parents=True)
    shutil.copy(micro_root / DATASET / "raw" / "manifest.json", root / DATASET / "raw" / "manifest.json")
    migrated_store(f"sqlite:///{root / 'mlflow.db'}")


def migrated_store(uri: str) -> None:
    """MLflow's tables in the new SQLite store ``uri``, made here: in a test process a copy of the session's
    migrated template (tests/conftest.py), so that a stage run in a subprocess finds them and does not run
    MLflow's chain of schema migrations again (1-2 CPU-s per new store). MLflow goes on as with a store it
    made: its schema check, then the Default experiment."""
    import mlflow.store.db.utils as dbu
    import sqlalchemy

    engine = sqlalchemy.create_engine(uri)
    try:
        dbu._initialize_tables(engine)
    finally:
        engine.dispose()


def build(out_root: Path, stages=PIPELINE) -> Path:
    for s in stages:
        skidbench(s, out_root, here=True)
    return out_root / DATASET


def snapshot(root: Path) -> dict[str, str]:
    """Content hash of every output file under ``root`` (not stamps, Hydra logs or MLflow stores)."""
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root).as_posix()
        if not p.is_file() or rel.startswith(("hydra/", "mlartifacts/", "mlflow")) or "/.stamps/" in rel:
            continue
        if p.name in (".stamp.json",) or "/.stamps" in "/" + rel:
            continue
        data = p.read_bytes()
        if p.suffix == ".json":  # wall-clock timings are the only fields allowed to differ
            data = json.dumps(_drop(json.loads(data), TIMING_KEYS), sort_keys=True).encode()
        out[rel] = hashlib.blake2b(data, digest_size=16).hexdigest()
    return out


TIMING_KEYS = {"seconds", "fit_time_s", "predict_time_s"}


def _drop(obj, keys):
    if isinstance(obj, dict):
        return {k: _drop(v, keys) for k, v in obj.items() if k not in keys}
    if isinstance(obj, list):
        return [_drop(v, keys) for v in obj]
    return obj


def tmp_files(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob(".tmp-*"))
