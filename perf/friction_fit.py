"""Friction model: the fit before issue 14 against today's, in one process on the same data (``make bench``).

Data: the ``scaling`` comparison's 16x case (32 synthetic Train sequences of 1,500 rows, 48,000 rows; ground
truth from an extended differential drive with side slip and noise, so the friction model is not the
truth), read back from split files and fitted as :func:`skidbench.models.fitting.fit.fit_model` fits it
(configured initial parameters and options). ``quick``: the 1x case (3,000 rows).

- old: ``perf/friction_legacy.py``, the version-1.5 solve and fit frozen (finite-difference
  Jacobians inside the Levenberg-Marquardt and for the five parameters);
- new: ``FrictionBased.fit`` (compiled per-step solve with the analytic Jacobian, implicit-function
  parameter Jacobian).

Times are CPU seconds of this process with one BLAS thread. The compiled kernels are loaded (or compiled,
on a fresh checkout) by a small solve before the clock starts; that one-off cost is reported separately
(``kernel_load_s``). Both fits minimise the same objective (soft_l1 on the velocity error of the steps
with a root at the start); ``robust_cost_*`` evaluates it at each fit's parameters with the same solve, so
the two answers are compared on one scale, and ``fit_loss_*`` is the reported mean squared error.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from . import register

SEQ_ROWS = 1500


def training_table(n_seq: int, seq_rows: int = SEQ_ROWS):
    """(robot, initial params, options, Train table) of the scaling comparison's data with ``n_seq``
    sequences."""
    from hydra import initialize_config_module

    from skidbench.models.fitting.fit import ModelConfigs, build_model
    from skidbench.pipeline.core.layout import layout_from_cfg
    from skidbench.pipeline.core.robot import robot_from_hydra
    from skidbench.pipeline.core.schema import concat_sequences, list_split_files, read_split

    from .scaling import _compose, write_splits

    with (
        tempfile.TemporaryDirectory(prefix="skidbench-friction-fit-") as tmp,
        initialize_config_module("skidbench.conf", version_base="1.3"),
    ):
        dataset = f"friction-fit-{n_seq}"
        cfg = _compose(Path(tmp), dataset)
        robot = robot_from_hydra(cfg.robot)
        write_splits(Path(tmp), robot, dataset, n_seq, seq_rows)
        files = list_split_files(layout_from_cfg(cfg).splits, "tile", "train")
        train = concat_sequences([read_split(p) for p in files])
        model = build_model(ModelConfigs.from_cfg(cfg), "friction", robot)
        return robot, dict(model.params), dict(model.options), train


def robust_cost(model, table, params: dict) -> float:
    """The fit's objective at ``params``: soft_l1 (scale ``f_scale``) of the velocity error over the steps
    with a root under the model's initial parameters (the scored steps), by the current solve."""
    from skidbench.models.columns import targets, training_rows

    train = training_rows(table)
    inp = model.inputs(train)
    y = targets(train)
    _, start = model.velocities(inp, model.params)
    scored = start.status == 1
    v, _ = model.velocities(inp, {**model.params, **params})
    f_scale = float(model.options.get("f_scale", 0.1))
    z = ((v - y)[scored] / f_scale) ** 2
    return float(0.5 * f_scale**2 * np.sum(2.0 * (np.sqrt(1.0 + z) - 1.0)))


def compare(n_seq: int) -> dict[str, Any]:
    from threadpoolctl import threadpool_limits

    from skidbench.models.friction.balance import FrictionGeometry
    from skidbench.models.friction.model import FrictionBased
    from skidbench.models.friction.solver import solve

    from .friction_legacy import LegacyFrictionFit

    robot, params, options, train = training_table(n_seq)
    out: dict[str, Any] = {"rows": len(train)}
    with threadpool_limits(1):
        c = time.process_time()
        one = np.ones(4)
        solve(one, one, one, one, params, FrictionGeometry.from_robot(robot))
        out["kernel_load_s"] = time.process_time() - c
        fitted = {}
        for tag, cls in (("new", FrictionBased), ("old", LegacyFrictionFit)):
            model = cls(robot, params, **options)
            c, w = time.process_time(), time.perf_counter()
            model.fit(train)
            out[f"fit_cpu_{tag}_s"] = time.process_time() - c
            out[f"fit_wall_{tag}_s"] = time.perf_counter() - w
            out[f"fit_loss_{tag}"] = model.fit_loss_
            out[f"nfev_{tag}"] = model.fit_info_["nfev"]
            # every digit: a change to the solve is checked against the fit to the bit (docs/performance.md)
            out[f"params_{tag}"] = " ".join(f"{k}={v!r}" for k, v in model.params.items())
            fitted[tag] = model
        judge = FrictionBased(robot, params, **options)
        for tag, model in fitted.items():
            out[f"robust_cost_{tag}"] = robust_cost(judge, train, model.params)
    new, old = fitted["new"], fitted["old"]
    out["speed_ratio"] = out["fit_cpu_old_s"] / out["fit_cpu_new_s"]
    out["fit_loss_rel_diff"] = (new.fit_loss_ - old.fit_loss_) / old.fit_loss_
    out["robust_cost_rel_diff"] = (out["robust_cost_new"] - out["robust_cost_old"]) / out["robust_cost_old"]
    out["params_max_rel_diff"] = max(
        abs(new.params[k] - old.params[k]) / abs(old.params[k]) for k in old.params
    )
    return out


@register(
    "friction_fit",
    "friction model fit: v1.5 (finite-difference Jacobians, frozen in friction_legacy.py) vs today's, one "
    "process, the scaling data at 16x (48,000 rows); CPU s, loss, parameters",
    targets={
        "fit_cpu_new_s": ("<=", 15.0),
        "speed_ratio": (">=", 10.0),
        "robust_cost_rel_diff": ("<=", 1e-6),
    },
)
def friction_fit(quick: bool) -> dict[str, Any]:
    return compare(2 if quick else 32)
