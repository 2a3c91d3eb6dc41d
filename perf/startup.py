"""The fixed cost of a ``skidbench`` command: what every stage pays before its own work (the interpreter,
the imports, Hydra's composes), the cost a test suite that spawns commands pays per command.

Each command runs ``n`` times (9; ``--quick``: 3) in a fresh process with an empty output root, the
commands interleaved so that a change of the machine's load hits them alike; the medians of wall time and
of CPU time (user + system of the command and the processes it waited for, ``RUSAGE_CHILDREN``) are
reported. CPU time is the figure to compare on a shared machine: wall time carries the other jobs' load.

- ``python``: ``python -c pass``, the interpreter's own start (the floor);
- ``help``: ``skidbench --help`` (the command-line module alone);
- ``datasets``: ``skidbench datasets`` on an empty root (a whole stage: its imports, three composes, the
  run);
- ``<stage>_cfg``: ``skidbench <stage> --cfg job scale=tiny``: the stage's module imported, its overrides
  checked and the config composed and printed, nothing run;
- ``import_<stage>``: the CPU time of importing the stage's module alone (``python -c 'import ...'`` minus
  ``python -c pass``).
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from . import register

BIN = Path(sys.executable).parent
COMMANDS: dict[str, list[str]] = {
    "python": [sys.executable, "-c", "pass"],
    "help": [str(BIN / "skidbench"), "--help"],
    "datasets": [str(BIN / "skidbench"), "datasets"],
    **{
        f"{s}_cfg": [str(BIN / "skidbench"), s, "--cfg", "job", "scale=tiny"]
        for s in ("extract", "split", "calibrate", "evaluate", "compare")
    },
}
MODULES = {
    "cli": "skidbench.pipeline.cli.main",
    "extract": "skidbench.pipeline.extract.app",
    "groundtruth": "skidbench.pipeline.groundtruth.app",
    "split": "skidbench.pipeline.splits.app",
    "calibrate": "skidbench.pipeline.calibrate.app",
    "evaluate": "skidbench.benchmark.evaluate.app",
    "compare": "skidbench.benchmark.board.app",
}


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def timed(cmd: list[str], env: dict[str, str]) -> tuple[float, float]:
    """(wall s, CPU s) of one run of ``cmd``; raises when it fails."""
    cpu, wall = _children_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    wall, cpu = time.perf_counter() - wall, _children_cpu() - cpu
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr.strip()[-300:]}")
    return wall, cpu


@register("startup", "the fixed cost of a skidbench command: interpreter, imports, composes (median)")
def startup(quick: bool) -> dict[str, Any]:
    n = 3 if quick else 9
    commands = dict(COMMANDS)
    commands.update({f"import_{k}": [sys.executable, "-c", f"import {m}"] for k, m in MODULES.items()})
    samples: dict[str, list[tuple[float, float]]] = {k: [] for k in commands}
    with tempfile.TemporaryDirectory(prefix="skidbench-startup-") as out:
        env = {**os.environ, "SKIDBENCH_OUT": out}
        env.pop("MLFLOW_TRACKING_URI", None)
        for _ in range(n):
            for name, cmd in commands.items():
                samples[name].append(timed(cmd, env))
    metrics: dict[str, Any] = {"runs": n}
    floor = statistics.median(c for _, c in samples["python"])
    for name, runs in samples.items():
        cpu = statistics.median(c for _, c in runs)
        if name.startswith("import_"):
            metrics[f"{name}_cpu_s"] = round(max(0.0, cpu - floor), 3)
            continue
        metrics[f"{name}_wall_s"] = round(statistics.median(w for w, _ in runs), 3)
        metrics[f"{name}_cpu_s"] = round(cpu, 3)
    return metrics
