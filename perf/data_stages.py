"""The data stages locally and as Ray tasks on a local multi-node cluster: CPU seconds per second of
driving, per stage (``make bench BENCH=data_stages``; docs/scaling.md's cost model).

One simulated dataset (``tiny``, or ``$SKIDBENCH_BENCH_SCALE``), then ``extract``, ``groundtruth`` (stereo
VO), ``split`` and ``calibrate``: once with the local forked workers, then, from the same raw bags, through
a Ray cluster on this machine (``ray start`` head and worker nodes on 127.0.0.1, one CPU each) of two
sizes. A stage's CPU is its process and every process it waited for (``wait4``) plus, on a cluster, every
process of the cluster over the stage (``/proc`` polled, as the ``sweep`` comparison does: raylets,
agents, task workers). The
outputs of the cluster runs are compared with the local run's (``same_outputs``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from . import register
from .reproduce import SCALE_ENV, run_stage
from .sweep import _ClusterCPU

STAGES = {
    "extract": ["extract.progress=false"],
    "groundtruth": ["groundtruth.method=vo"],
    "split": [],
    "calibrate": ["track=false"],
}
OUTPUTS = ("extracted", "groundtruth", "splits", "calibration", ".stamps", "dataset.json")


def _clear(ds: Path) -> None:
    for name in OUTPUTS:
        p = ds / name
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)


TIMING_KEYS = {"seconds", "fit_time_s", "predict_time_s"}  # wall-clock fields, the only ones that may differ


def _drop(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _drop(v) for k, v in obj.items() if k not in TIMING_KEYS}
    return [_drop(v) for v in obj] if isinstance(obj, list) else obj


def _digests(ds: Path) -> dict[str, str]:
    """A hash of each output of the data stages (stamps aside: they record when; JSON without its
    wall-clock timings)."""
    out = {}
    for p in sorted(ds.rglob("*")):
        rel = p.relative_to(ds).as_posix()
        if p.is_file() and rel.split("/")[0] in OUTPUTS and ".stamp" not in rel:
            data = p.read_bytes()
            if p.suffix == ".json":
                data = json.dumps(_drop(json.loads(data)), sort_keys=True).encode()
            out[rel] = hashlib.blake2b(data, digest_size=16).hexdigest()
    return out


def _driving_s(ds: Path) -> float:
    """Seconds of driving: the ground truth's duration summed over the sequences."""
    return sum(json.loads(p.read_text())["duration_s"] for p in (ds / "groundtruth").glob("*.json")
               if p.name != "loop_closure.json")  # fmt: skip


def _stages(scale: str, out_root: Path, cwd: Path, extra: list[str], cluster=None) -> dict[str, float]:
    """CPU seconds of each data stage (and of the cluster's processes over it)."""
    out = {}
    for stage, args in STAGES.items():
        polled = _ClusterCPU(cluster) if cluster else None
        res = run_stage(stage, [f"scale={scale}", *args, *extra], out_root, cwd, f"{stage}-{len(extra)}")
        used = polled.stop() if polled else 0.0
        if res["exit"]:
            raise RuntimeError(f"{stage} failed: {res.get('error')}")
        out[stage] = res["cpu_s"] + used
    return out


@register(
    "data_stages",
    "extract, groundtruth (VO), split and calibrate: local forked workers vs Ray tasks on a local cluster of "
    "2 and 3 nodes (1 CPU each); CPU s per second of driving per stage, the same outputs",
)
def data_stages(quick: bool) -> dict[str, Any]:
    from skidbench.pipeline.runner.cluster import local_cluster

    scale = os.environ.get(SCALE_ENV) or "tiny"
    metrics: dict[str, Any] = {"scale": scale}
    with tempfile.TemporaryDirectory(prefix="skidbench-data-stages-") as tmp:
        root = Path(tmp)
        out_root = root / "outputs"
        ds = out_root / f"sim-{scale}"
        sim = run_stage("simulate", [f"scale={scale}", "seed=0"], out_root, root)
        local = _stages(scale, out_root, root, [])
        driving = _driving_s(ds)
        reference = _digests(ds)
        metrics["driving_s"] = driving
        metrics["sequences"] = len(list((ds / "extracted").iterdir()))
        metrics["simulate_cpu_s_per_driving_s"] = sim["cpu_s"] / driving
        for stage, cpu in local.items():
            metrics[f"{stage}_local_cpu_s"] = cpu
            metrics[f"{stage}_local_cpu_s_per_driving_s"] = cpu / driving
        # a loopback-only cluster: no token authentication (Ray would write one under ~/.ray), no usage
        # reporting; the stages (drivers) need the same
        os.environ.update({"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"})
        env = {k: v for k, v in os.environ.items() if k != "SKIDBENCH_OUT"}
        for nodes in (2, 3):
            with local_cluster(num_cpus=1, env=env) as cluster:
                for _ in range(nodes - 1):
                    cluster.add_node(num_cpus=1)
                _clear(ds)
                ray = ["hydra/launcher=ray", f"hydra.launcher.address={cluster.address}"]
                cpu = _stages(scale, out_root, root, ray, cluster)
            differ = sorted(k for k, v in _digests(ds).items() if reference.get(k) != v)
            metrics[f"same_outputs_{nodes}_nodes"] = "yes" if not differ else f"no: {', '.join(differ[:3])}"
            for stage, c in cpu.items():
                metrics[f"{stage}_ray{nodes}_cpu_s"] = c
            metrics[f"total_ray{nodes}_over_local_cpu"] = sum(cpu.values()) / sum(local.values())
    return metrics
