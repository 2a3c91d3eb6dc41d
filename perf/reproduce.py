"""The whole ``make reproduce`` (simulate, extract, groundtruth, split, evaluate, compare) in a fresh out
root: wall time, CPU time and peak resident memory per stage; and extraction's peak memory on the
``mini`` vs the ``full`` simulated bags.

Scale: ``mini`` (what ``make reproduce`` runs); ``SKIDBENCH_BENCH_SCALE=tiny`` for a quick run (and
``--quick`` runs ``tiny`` too). ``SKIDBENCH_BENCH_MAX_MIN=<m>``: start no stage after ``m`` minutes (the
stages done are reported, the total says incomplete).

Each stage runs as ``skidbench <stage> scale=<s> seed=0`` in its own process, under a small wrapper
(``python -m perf.reproduce stage <json> <stage> [overrides]``) that runs the CLI
in-process (``runpy``, as ``python -m skidbench.pipeline.cli.main``) and at exit writes its own ``VmHWM`` (the
high-water mark of the stage's process image) and ``RUSAGE_CHILDREN``'s ``ru_maxrss`` (the largest process
the stage started and waited for, e.g. the simulator's workers). Not ``/usr/bin/time -v`` nor the
benchmark's own ``RUSAGE_CHILDREN``: a process started by fork/vfork+exec inherits its parent's resident
size as the floor of its ``ru_maxrss``, so those would report at least the size of the (Python) process that
started them. Peak per stage is the larger of the two figures: the largest single process, not the sum of
concurrent workers.
"""

from __future__ import annotations

import atexit
import json
import os
import resource
import runpy
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.layout import default_out_root

from . import child_env, register
from .harness import peak_rss_mb

#: the steps of ``make reproduce``: (label, stage, its extra arguments); evaluate runs twice, under the
#: paper's ``commanded`` inputs and under the calibrated wheel ``response`` (pipeline/core/protocol.py)
STEPS = (
    ("simulate", "simulate", ()),
    ("extract", "extract", ()),
    ("groundtruth", "groundtruth", ()),
    ("split", "split", ()),
    ("calibrate", "calibrate", ()),
    ("evaluate", "evaluate", ()),
    ("evaluate_response", "evaluate", ("inputs=response",)),
    ("compare", "compare", ()),
)
STAGES = tuple(label for label, _, _ in STEPS)
#: steps `make reproduce` runs side by side (pipeline/runner/side_by_side.py): started together, the next step
#: after the longer one; the total wall counts the longer one
SIDE_BY_SIDE = ("evaluate", "evaluate_response")
SCALE_ENV = "SKIDBENCH_BENCH_SCALE"
KEEP_ENV = "SKIDBENCH_BENCH_KEEP"  # a folder: the run's out root and stage logs are kept there (its numbers)
BUDGET_ENV = "SKIDBENCH_BENCH_MAX_MIN"  # stop starting stages after this many minutes (a loaded machine)


def run_stage(
    stage: str, args: list[str], out_root: Path, cwd: Path, label: str | None = None
) -> dict[str, Any]:
    """One stage in a fresh process under the wrapper: wall/CPU seconds, peak RSS (MiB), exit code."""
    env = child_env()  # the stage's cwd is its own folder: perf found through PYTHONPATH
    env["SKIDBENCH_OUT"] = str(out_root)
    env.pop("MLFLOW_TRACKING_URI", None)  # the fresh root's own mlflow.db
    with tempfile.NamedTemporaryFile(prefix="skidbench-stage-", suffix=".json", delete=False) as f:
        report = Path(f.name)
    cmd = [sys.executable, "-m", "perf.reproduce", "stage", str(report), stage, *args]
    log = cwd / f"{label or stage}.log"
    started = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - started
    try:
        mem = json.loads(report.read_text() or "{}")
    except (OSError, json.JSONDecodeError):
        mem = {}
    report.unlink(missing_ok=True)
    res = {
        "stage": label or stage,
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,  # the stage and every process it waited for
        "peak_rss_mb": max(mem.get("self_mb", 0.0), mem.get("children_mb", 0.0)),
        "self_rss_mb": mem.get("self_mb"),
        "children_rss_mb": mem.get("children_mb"),
        "exit": proc.returncode,
    }
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:] or ["no output"]
        res["error"] = tail[0][:300]
    return res


def reproduce(scale: str, keep: Path | None = None, budget_min: float | None = None) -> dict[str, Any]:
    """Every stage of ``make reproduce`` (simulated source) in a fresh out root; stops at a failure, and
    with ``budget_min`` does not start a stage once that many minutes have passed (``stopped``)."""
    with tempfile.TemporaryDirectory(prefix="skidbench-reproduce-") as tmp:
        root = Path(keep) if keep else Path(tmp)
        out_root = root / "outputs"
        out_root.mkdir(parents=True, exist_ok=True)
        stages = []
        stopped = None
        started = time.perf_counter()
        for group in _groups():
            if budget_min is not None and time.perf_counter() - started > 60.0 * budget_min:
                stopped = f"budget of {budget_min:g} min spent before {group[0][0]}"
                break
            with ThreadPoolExecutor(len(group)) as pool:  # each thread waits for its stage's process
                results = list(
                    pool.map(
                        lambda step: run_stage(step[1], [f"scale={scale}", "seed=0", *step[2]], out_root,
                                               root, step[0]),
                        group,
                    )
                )  # fmt: skip
            for res in results:
                res["side_by_side"] = len(group) > 1
                stages.append(res)
                print(
                    f"perf reproduce: {res['stage']} {res['wall_s']:.1f} s, {res['peak_rss_mb']:.0f} MiB"
                    + (f" FAILED: {res.get('error')}" if res["exit"] else ""),
                    file=sys.stderr,
                    flush=True,
                )
            if any(res["exit"] != 0 for res in results):
                break
        bags = sorted((out_root / f"sim-{scale}" / "raw" / "bags").glob("*"))
        return {"scale": scale, "stages": stages, "bags": len(bags), "stopped": stopped}


def _groups() -> list[list[tuple]]:
    """:data:`STEPS` in the order `make reproduce` runs them: one step at a time, the
    :data:`SIDE_BY_SIDE` steps together."""
    groups: list[list[tuple]] = []
    for step in STEPS:
        if step[0] in SIDE_BY_SIDE and groups and groups[-1][0][0] in SIDE_BY_SIDE:
            groups[-1].append(step)
        else:
            groups.append([step])
    return groups


def extraction_mini_vs_full() -> dict[str, Any]:
    """Extraction's peak RSS on the longest ``sim-mini`` and ``sim-full`` bags under the default out root
    (each in a fresh interpreter; see ``extraction.measure_rss``), when they have been simulated."""
    from .extraction import _sim_bags, measure_rss

    bags = _sim_bags()
    out: dict[str, Any] = {}
    for scale in ("mini", "full"):
        path = bags.get(scale)
        if path is None:
            where = default_out_root() / f"sim-{scale}"
            if where.is_relative_to(Path.cwd()):  # the results table is committed: no machine's paths in it
                where = where.relative_to(Path.cwd())
            out[f"extract_rss_{scale}_mb"] = f"not measured ({where} not simulated)"
            continue
        size = sum(f.stat().st_size for f in [path, *path.glob("*")]) / 2**20
        res = measure_rss(path, "sim")
        out[f"extract_rss_{scale}_mb"] = res["peak_rss_mb"]
        out[f"extract_{scale}_bag"] = f"{path.name} ({size:.0f} MiB, {res['messages']} messages)"
    if isinstance(out.get("extract_rss_mini_mb"), float) and isinstance(
        out.get("extract_rss_full_mb"), float
    ):
        out["extract_rss_full_minus_mini_mb"] = out["extract_rss_full_mb"] - out["extract_rss_mini_mb"]
    return out


def metrics(run: dict[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {"scale": run["scale"]}
    for s in run["stages"]:
        out[f"{s['stage']}_wall_s"] = s["wall_s"]
        out[f"{s['stage']}_cpu_s"] = s["cpu_s"]
        out[f"{s['stage']}_peak_rss_mb"] = s["peak_rss_mb"]
        if s["exit"]:
            out[f"{s['stage']}_error"] = s.get("error", f"exit {s['exit']}")
    done = [s for s in run["stages"] if s["exit"] == 0]
    out["stages_ok"] = f"{len(done)}/{len(STAGES)}"
    if run.get("stopped"):
        out["stopped"] = run["stopped"]
    # the total only counts when every stage ran (a failed run has no meaningful total); stages run side by
    # side count once, as the longer of them
    side = [s["wall_s"] for s in run["stages"] if s.get("side_by_side")]
    total = sum(s["wall_s"] for s in run["stages"] if not s.get("side_by_side")) + max(side, default=0.0)
    out["total_wall_min"] = total / 60.0 if len(done) == len(STAGES) else f"incomplete ({total / 60:.1f} min)"
    out["total_cpu_min"] = sum(s["cpu_s"] for s in run["stages"]) / 60.0
    out["max_peak_rss_mb"] = max((s["peak_rss_mb"] for s in run["stages"]), default=0.0)
    return out


@register(
    "reproduce",
    "make reproduce (simulated source) in a fresh out root: wall/CPU time and peak RSS per stage "
    f"(scale mini; {SCALE_ENV}=tiny for a quick run); extraction RSS on mini vs full bags",
    targets={"total_wall_min": ("<", 3.0)},  # issue 31: a first `make reproduce` under 3 min (quiet machine)
)
def reproduce_bench(quick: bool) -> dict[str, Any]:
    scale = os.environ.get(SCALE_ENV) or ("tiny" if quick else "mini")
    budget = os.environ.get(BUDGET_ENV)
    keep = os.environ.get(KEEP_ENV)
    out = metrics(
        reproduce(scale, Path(keep) if keep else None, budget_min=float(budget) if budget else None)
    )
    out.update(extraction_mini_vs_full())
    return out


# -------------------------------------------------------------------------------------------------
# the per-stage wrapper (child process)


def _stage_main(report: str, stage: str, args: list[str]) -> None:
    def write() -> None:
        children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0  # KiB on Linux
        Path(report).write_text(json.dumps({"self_mb": peak_rss_mb(), "children_mb": children}))

    atexit.register(write)
    # the CLI run as a program, in this process (``python -m skidbench.pipeline.cli.main <stage> ...``): the
    # harness measures the command line itself, run by name as a user runs it, not imported; in this
    # process, because a subprocess would inherit this process's size as its RSS floor (above)
    sys.argv = ["skidbench", stage, *args]
    runpy.run_module("skidbench.pipeline.cli.main", run_name="__main__", alter_sys=True)


if __name__ == "__main__":
    if len(sys.argv) >= 4 and sys.argv[1] == "stage":
        _stage_main(sys.argv[2], sys.argv[3], sys.argv[4:])
    else:
        print("usage: python -m perf.reproduce stage <report.json> <stage> [args]")
        sys.exit(2)
