"""Friction model: batched inner solve vs the paper's per-step scipy trust-region solve (``make bench``).
Times are CPU seconds of this process (the machine may be shared).

``compare()`` runs both on the same random but realistic steps (Jackal, |v| <= 1.5 m/s, |w| <= 2 rad/s,
commanded accelerations ~ N(0, 1) m/s^2 and N(0, 3) rad/s^2). The per-step reference is too slow for
100,000 steps: it runs on the first ``ref_max`` steps and its time is extrapolated linearly (said in the
result, ``reference_extrapolated``). Agreement is the max |velocity difference| over the steps where both
found a root, and separately over those where no tractive force saturates (where the root is unique).
The batched solve's compiled kernels are loaded (compiled on a fresh checkout) by a small solve before the
clock starts; that one-off cost per process is reported as ``kernel_load_s``.
"""

from __future__ import annotations

import time

import numpy as np

from skidbench.models.friction.balance import FrictionGeometry, body_velocity
from skidbench.models.friction.model import DEFAULT_PARAMS
from skidbench.models.friction.solver import solve, solve_reference


def _jackal():
    from skidbench.pipeline.core.robot import load_robot

    return load_robot("jackal")


def random_steps(robot, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    wl, wr = robot.wheel_rates_from_twist(rng.uniform(-1.5, 1.5, n), rng.uniform(-2, 2, n))
    dwl, dwr = robot.wheel_rates_from_twist(rng.normal(0, 1.0, n), rng.normal(0, 3.0, n))
    return wl, wr, dwl, dwr


def compare(
    n_steps=(10_000, 100_000), ref_max: int = 1000, seed: int = 0, robot=None, params=None
) -> list[dict]:
    """One dict per size: time_batched_s, time_reference_s (measured or extrapolated), speed_ratio,
    max_velocity_diff (both roots), max_velocity_diff_unique (both roots, unsaturated), non-converged and
    no-root counts for each solver (reference counts on its subsample)."""
    robot = robot or _jackal()
    params = params or DEFAULT_PARAMS
    geo = FrictionGeometry.from_robot(robot)
    t0 = time.process_time()
    solve(*random_steps(robot, 4, seed), params, geo)
    load = time.process_time() - t0
    out = []
    for n in n_steps:
        inp = random_steps(robot, n, seed)
        t0 = time.process_time()
        fast = solve(*inp, params, geo)
        tb = time.process_time() - t0
        m = min(n, ref_max)
        sub = tuple(a[:m] for a in inp)
        t0 = time.process_time()
        ref = solve_reference(*sub, params, geo)
        tr = (time.process_time() - t0) * n / m
        vf = body_velocity(fast.theta[:m], sub[0], sub[1], geo.r, geo.B)
        vr = body_velocity(ref.theta, sub[0], sub[1], geo.r, geo.B)
        both = (fast.status[:m] == 1) & (ref.status == 1)
        unique = both & ~ref.saturated(sub[0], sub[1], params)
        diff = np.max(np.abs(vf - vr), axis=1)
        out.append(
            {
                "n_steps": n,
                "kernel_load_s": load,
                "reference_steps": m,
                "reference_extrapolated": m < n,
                "time_batched_s": tb,
                "time_reference_s": tr,
                "speed_ratio": tr / tb,
                "max_velocity_diff": float(diff[both].max(initial=0.0)),
                "max_velocity_diff_unique": float(diff[unique].max(initial=0.0)),
                "both_root": int(both.sum()),
                "batched_not_converged": fast.n_not_converged,
                "batched_no_root": int(np.sum(fast.status == 2)),
                "batched_iterations": fast.n_iter,
                "reference_not_converged": ref.n_not_converged,
                "reference_no_root": int(np.sum(ref.status == 2)),
            }
        )
    return out


def main() -> None:
    for row in compare():
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))


try:  # the `make bench` harness (perf/__init__.py) collects registered comparisons
    from . import register
except ImportError:  # run as a script
    register = None

if register is not None:

    @register(
        "friction_solver",
        "friction model: batched LM inner solve vs per-step scipy least_squares(trf) (reference on a "
        "1,000-step subsample, time extrapolated)",
        targets={
            "speed_ratio_10k": (">=", 100),
            "speed_ratio_100k": (">=", 1000),
            "max_velocity_diff_10k": ("<", 1e-9),
            "max_velocity_diff_100k": ("<", 1e-9),
        },
    )
    def friction_solver(quick: bool) -> dict[str, float]:
        sizes = (10_000,) if quick else (10_000, 100_000)
        rows = compare(sizes, ref_max=200 if quick else 1000)
        out: dict[str, float] = {}
        for row in rows:
            tag = f"{row['n_steps'] // 1000}k"
            for k in (
                "speed_ratio",
                "max_velocity_diff",
                "time_batched_s",
                "time_reference_s",
                "batched_not_converged",
                "batched_no_root",
                "reference_not_converged",
                "reference_no_root",
                "both_root",
            ):
                out[f"{k}_{tag}"] = row[k]
        out["kernel_load_s"] = rows[0]["kernel_load_s"]
        return out


if __name__ == "__main__":
    main()
