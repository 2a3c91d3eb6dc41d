"""Runs the registered comparisons, each in its own Python process (so one comparison's allocations,
caches and imports never colour the next, and the machine's drift hits both sides of a ratio alike),
then writes ``perf/results/latest.json`` and ``latest.md`` and prints the table.

    python -m perf                 # every comparison (from the repository root)
    python -m perf extraction      # some
    python -m perf --quick         # small problems (a smoke run)
    python -m perf --list
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

from skidbench.pipeline.core.io import write_json_atomic, write_text_atomic

from . import check, child_env, load_all

RESULTS = Path(__file__).resolve().parent / "results"


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MiB).

    Linux's ``VmHWM`` (the high-water mark of this process image); not ``ru_maxrss``, which a process
    started with fork+exec inherits from its parent's size at the fork, a floor that would hide what
    the child itself used."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0  # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def run_one(name: str, quick: bool) -> dict[str, Any]:
    """Run one comparison in this process; its metrics plus wall time and peak memory."""
    comparisons = load_all()
    started = time.perf_counter()
    metrics = comparisons[name].func(quick)
    return {
        "metrics": metrics,
        "seconds": round(time.perf_counter() - started, 2),
        "peak_rss_mb": peak_rss_mb(),
    }


def run_in_subprocess(name: str, quick: bool, timeout_s: float) -> dict[str, Any]:
    """Run one comparison in a fresh interpreter and collect its JSON result (or its error)."""
    with tempfile.TemporaryDirectory(prefix="skidbench-bench-") as tmp:
        out = Path(tmp) / "result.json"
        cmd = [sys.executable, "-m", "perf.harness", "--one", name, "--json", str(out)]
        if quick:
            cmd.append("--quick")
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=child_env())
        except subprocess.TimeoutExpired:
            return {"error": f"timed out after {timeout_s:.0f} s"}
        if proc.returncode != 0 or not out.is_file():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            return {"error": f"exit {proc.returncode}: {tail[0]}"}
        return json.loads(out.read_text())


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        if value != 0 and (abs(value) < 1e-3 or abs(value) >= 1e6):
            return f"{value:.2e}"
        return f"{value:.3g}" if abs(value) < 100 else f"{value:.1f}"
    return str(value)


def markdown(results: dict[str, Any]) -> str:
    """The results as a Markdown table: one row per metric, targets and whether each is met."""
    lines = [
        f"Performance ({results['date']}, {results['machine']}, {results['cpus']} CPUs)",
        "",
        "| comparison | metric | value | target | met |",
        "|---|---|---|---|---|",
    ]
    for name, res in results["comparisons"].items():
        if "error" in res:
            lines.append(f"| {name} | error | {res['error']} | | no |")
            continue
        targets = res.get("targets", {})
        for metric, value in res["metrics"].items():
            target = targets.get(metric)
            met = "" if target is None else {True: "yes", False: "**no**", None: "?"}[check(value, target)]
            tgt = "" if target is None else f"{target[0]} {_fmt(target[1])}"
            lines.append(f"| {name} | {metric} | {_fmt(value)} | {tgt} | {met} |")
        lines.append(
            f"| {name} | wall time (s) / peak RSS (MiB) | {res['seconds']} / {res['peak_rss_mb']:.0f} | | |"
        )
    return "\n".join(lines) + "\n"


def _previous(path: Path) -> dict[str, Any]:
    try:
        return dict(json.loads(path.read_text()).get("comparisons", {}))
    except (OSError, json.JSONDecodeError, AttributeError):
        return {}


def run_all(names: list[str], quick: bool, timeout_s: float, results_dir: Path) -> dict[str, Any]:
    comparisons = load_all()
    unknown = [n for n in names if n not in comparisons]
    if unknown:
        raise SystemExit(f"unknown comparison(s): {', '.join(unknown)} (have: {', '.join(comparisons)})")
    results: dict[str, Any] = {
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{platform.machine()} {platform.processor() or platform.system()}".strip(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "quick": quick,
        "comparisons": {},
    }
    if names:  # a partial run keeps the other comparisons' last results (each carries its date)
        results["comparisons"].update(_previous(results_dir / "latest.json"))
    for name in names or list(comparisons):
        print(f"perf: {name} ...", file=sys.stderr, flush=True)
        res = run_in_subprocess(name, quick, timeout_s)
        res["date"] = results["date"]
        comp = comparisons[name]
        res["description"] = comp.description
        res["targets"] = {k: list(v) for k, v in comp.targets.items()}
        if "metrics" in res:
            res["met"] = {k: check(res["metrics"].get(k), v) for k, v in comp.targets.items()}
        results["comparisons"][name] = res
    results_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(results_dir / "latest.json", results)
    table = markdown(results)
    write_text_atomic(results_dir / "latest.md", table)
    print(table)
    return results


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m perf", description=__doc__.split("\n")[0])
    parser.add_argument("names", nargs="*", help="comparisons to run (default: all)")
    parser.add_argument("--quick", action="store_true", help="small problems (smoke run)")
    parser.add_argument("--list", action="store_true", help="list the comparisons and exit")
    parser.add_argument("--timeout", type=float, default=1800.0, help="per comparison (s)")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder for latest.json / latest.md")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:  # child process: run one comparison, write its result
        try:
            res = run_one(args.one, args.quick)
        except Exception:
            traceback.print_exc()
            sys.exit(1)
        write_json_atomic(args.json, res)
        return
    if args.list:
        for name, comp in load_all().items():
            print(f"{name}: {comp.description}")
        return
    run_all(args.names, args.quick, args.timeout, args.results)


if __name__ == "__main__":
    main()
