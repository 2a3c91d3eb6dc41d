"""Is a speed deficit a scale, and is the ground truth's distance scale steady? What discovery's two
checks of speed (``benchmark/discovery/checks/scale.py``, ``scale_by_speed``;
``benchmark/discovery/checks/ground_truth.py``, ``scale_drift_finding``) see on worlds whose truth is
known (docs/discovery.md, steps 1 and 2):

    python -m perf.discover_scale [--seeds 2] [--publish]      # from the repository root

Per world (``tests/discover_data.py`` through the split stage's code, as ``perf.discover_fdr`` makes them;
the base ``edd`` at the spec sheet's radius, as when ``calibrate`` could not measure it): the one scale
of the forward speed, the scales of the slow and the fast half of the moving rows, their spread as a
share of the deficit (``discover.scale_spread`` is the threshold), the sign-flip p-value over held-out
units, and the verdict; the RMS drift of the distance scale and of the yaw rate against the commands
(percent about each sequence's mean) and whether it is a ground-truth finding. Worlds: a 0.96 speed scale
alone and with each catalogue effect (the ``curvy`` drive, few straight rows), a command dead zone, a
load-dependent wheel-rate limit, clean data (the three noise levels of the odometry-like truth), a slowly
varying slip, a robot slowing down (``speed_fade``), a payload, and a ground truth whose distance scale
drifts 15 % per minute.
``--publish`` writes ``perf/results/discover_scale.md``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

import numpy as np

from perf.discover_fdr import REPO, _dd, tables


def worlds(seeds: int) -> list[tuple[str, dict]]:
    """(name, the case of ``perf.discover_fdr.tables``) of every world measured."""
    dd = _dd()
    base = {"world": "kinematic", "noise": "default", "style": "curvy", "n_train": 8, "duration": 36.0}
    out = []
    for i in range(seeds):
        out.append(
            (f"speed scale 0.96 (seed {7000 + i})", {**base, "effect": "speed_scale", "seed": 7000 + i})
        )
    for j, e in enumerate(dd.DEFAULT_SIZES):
        out.append((f"speed scale 0.96 + {e}", {**base, "effect": ("speed_scale", e), "seed": 7100 + j}))
    for i in range(seeds):
        for e in ("command_dead_zone", "load_wheel_limit"):
            out.append((f"{e} (seed {7200 + i})", {**base, "style": "mixed", "effect": e, "seed": 7200 + i}))
        for noise in ("low", "default", "high"):
            clean = {**base, "style": "mixed", "noise": noise, "effect": None, "seed": 7300 + i}
            out.append((f"clean, {noise} noise (seed {7300 + i})", clean))
    for e in ("slow_slip", "speed_fade", "payload_change"):
        out.append((e, {**base, "style": "mixed", "effect": e, "seed": 7400}))
    out.append(("ground truth scale drift 15 %/min", {**base, "style": "mixed", "effect": None, "seed": 7500,
                                                       "world": "gt_scale"}))  # fmt: skip
    return out


def measure(case: dict) -> dict:
    from skidbench.benchmark.discovery.checks.ground_truth import drift_estimate, scale_drift_finding
    from skidbench.benchmark.discovery.checks.scale import scale_by_speed
    from skidbench.benchmark.discovery.pool import prepare_pool
    from skidbench.benchmark.discovery.search import fit_base
    from skidbench.models.augmented.fit import DiscoverSettings, build_pool
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.core.robot import load_robot

    dd = _dd()
    jackal, edd, s = load_robot("jackal"), get_model_class("edd"), DiscoverSettings()
    effects = (
        case["effect"] if isinstance(case["effect"], tuple) else [case["effect"]] if case["effect"] else []
    )
    orig = dd.hidden
    dd.hidden = lambda names: orig(effects)  # tables() asks for one effect; a world may hold two
    try:
        train = tables({**case, "effect": effects[0] if effects else None})
    finally:
        dd.hidden = orig
    pool = prepare_pool(build_pool(train, s), "commanded", jackal)
    drift = drift_estimate(pool)  # the sizes, always
    found = scale_drift_finding(pool)[1] is not None
    run = fit_base(pool, lambda: edd(jackal), jackal, s, "tile", "edd", lambda m: None)
    return scale_by_speed(pool, run.state.pred, s) | {"drift": drift, "gt_finding": found}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m perf.discover_scale", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--seeds", type=int, default=2, help="datasets of the scale, dead-zone, limit and clean worlds"
    )
    ap.add_argument("--publish", action="store_true", help="also write perf/results/discover_scale.md")
    a = ap.parse_args(argv)
    started = time.process_time()
    lines = [
        "| world | one scale | slow half | fast half | spread / deficit | p (sign flips) | a scale "
        "| distance scale drift (RMS %) | yaw rate drift (RMS %) | ground-truth finding |",
        "|---|---:|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    for name, case in worlds(a.seeds):
        r = measure(case)
        k = r["k"]
        spread = abs(r["scale_slow"] - r["scale_fast"]) / max(abs(k), 1e-12)
        lines.append(
            f"| {name} | {1 + k:.4f} | {r['scale_slow']:.4f} | {r['scale_fast']:.4f} | {spread:.2f} | "
            f"{r['p_value']:.3g} | {'yes' if r['proportional'] else 'no'} | {r['drift']['rms_pct']:.2f} | "
            f"{r['drift']['yaw_rate_rms_pct']:.2f} | {'yes' if r['gt_finding'] else 'no'} |"
        )
        print(lines[-1], flush=True)
    command = "python -m perf.discover_scale " + " ".join(sys.argv[1:] if argv is None else argv)
    cpu = time.process_time() - started
    text = (
        f"speed deficit by speed ({time.strftime('%Y-%m-%d')}): `{command.strip()}`, {cpu:.0f} CPU-s\n\n"
        + "\n".join(lines)
        + "\n\nThe spread of clean worlds is a share of a deficit near 0 (no scale passes the rule there). "
        "A ground-truth finding needs a distance-scale drift of at least 1.5 % RMS and a yaw-rate drift of "
        "at most half of it, corrected distances within half and twice the measured ones, and a drift that "
        "noise (the residual's sign flipped in 6 s blocks) gives at most 0.1 % of the time.\n"
    )
    if a.publish:
        from skidbench.pipeline.core.io import write_text_atomic

        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()  # fmt: skip
        write_text_atomic(REPO / "perf" / "results" / "discover_scale.md", f"Commit {commit}.\n\n" + text)
    print(text)


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
