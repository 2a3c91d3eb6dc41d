"""A sparse Gaussian process of the residual body velocities of a kinematic base model, after Trivedi et
al., "A Probabilistic Motion Model for Skid-Steer Wheeled Mobile Robot Navigation on Off-Road Terrains"
(ICRA 2024; RIVeR-Lab/multiterrain-gp-model).

What their code does (``src/all_data.py``, ``create_gp_train_test.py``, ``train_gp.py``), carried over:
- the GP's output is the residual of a nominal model: measured velocity - the nominal model's (theirs a
  dynamic unicycle, one step ahead; here a kinematic base model, default ``edd``, option ``base``);
  one GP per output (theirs linear and angular velocity; here vx, vy and wz);
- its inputs are the commanded linear and angular velocity and the robot's current linear and angular
  velocity, standardised (zero mean, unit variance per input). At predict time our input protocol gives
  no measured velocity, and under a first-order response the gap between command and current velocity
  is the acceleration times the time constant, so the "current velocity" pair is replaced by the
  commanded body acceleration (from ``cmd_dwl``/``cmd_dwr``): inputs (cmd_v, cmd_w, dv, dw);
- zero prior mean, a scaled squared-exponential kernel with one length scale per input (ARD) plus a
  Gaussian noise, hyperparameters by maximum marginal likelihood;
- rows where the robot is commanded to stand still are left out of training (theirs drop
  |cmd_lin| < 0.01 m/s; pivot turns are kept here: a skid-steer turns on the spot);
- their training set is 500 points: the one nearest each centroid of a 500-component mixture clustering
  of the inputs.

The approximation, and why: those cluster points are the inducing inputs Z (m = ``n_inducing``, k-means
centroids' nearest rows: same selection without scikit-learn), the hyperparameters maximise the exact
marginal likelihood on them (m x m Cholesky per evaluation), and the posterior is the deterministic
training conditional (DTC / projected process, Seeger et al. 2003) on EVERY valid Train row, accumulated
in chunks: O(N m^2) time, O(m^2 + chunk m) memory. A subset of data alone would throw away all but m rows;
an exact GP on 10^5 rows needs 80 GB. Predictive variance per output:
sigma_n^2 + k** - k*^T Kmm^-1 k* + k*^T A^-1 k*, A = Kmm + sigma_n^-2 Kmn Knm (computed whitened).
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import pandas as pd
from scipy.cluster.vq import kmeans2
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import minimize

from .base import KinematicModel, ModelError
from .columns import TARGETS, col, error_autocorrelation, mse, sequence_starts, targets
from .specs import get_model_class

try:  # installed with scipy's and scikit-learn's stacks; optional here
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None

FEATURE_NAMES = ("cmd_v", "cmd_w", "cmd_dv", "cmd_dw")


def _one_blas_thread():
    """The GP's BLAS calls are on m x m and m x 8192 blocks, where a multi-threaded BLAS on a shared
    2-core machine spends more time handing work between threads than computing (measured: a 48k-row fit
    42 s with OpenBLAS's default threads, 3.6 s with one)."""
    return threadpool_limits(1, "blas") if threadpool_limits is not None else contextlib.nullcontext()


CHUNK = 8192  # rows per block of the O(N m^2) accumulation: bounded memory


def gp_features(table: pd.DataFrame, robot) -> np.ndarray:
    """(T, 4) GP inputs: commanded body velocity (m/s, rad/s) and acceleration (m/s^2, rad/s^2) of the
    protocol's wheel rates."""
    v, w = robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))
    dv, dw = robot.twist_from_wheel_rates(col(table, "cmd_dwl"), col(table, "cmd_dwr"))
    return np.column_stack([v, w, dv, dw])


def se_kernel(a: np.ndarray, b: np.ndarray, lengthscales: np.ndarray, signal_var: float) -> np.ndarray:
    """ARD squared-exponential kernel matrix (len(a), len(b))."""
    a, b = a / lengthscales, b / lengthscales
    d2 = np.sum(a**2, 1)[:, None] + np.sum(b**2, 1)[None, :] - 2.0 * a @ b.T
    return signal_var * np.exp(-0.5 * np.maximum(d2, 0.0))


def neg_log_marginal(theta: np.ndarray, X: np.ndarray, y: np.ndarray) -> tuple[float, np.ndarray]:
    """Exact GP negative log marginal likelihood and its gradient in theta = log(lengthscales...,
    signal variance, noise variance) (Rasmussen & Williams eq. 5.9)."""
    ls, sf, sn = np.exp(theta[:-2]), np.exp(theta[-2]), np.exp(theta[-1])
    Kse = se_kernel(X, X, ls, sf)
    K = Kse + (sn + 1e-8) * np.eye(len(X))
    try:
        L = np.linalg.cholesky(K)
    except np.linalg.LinAlgError:
        return 1e25, np.zeros_like(theta)
    alpha = cho_solve((L, True), y)
    nlml = float(0.5 * y @ alpha + np.sum(np.log(np.diag(L))) + 0.5 * len(y) * np.log(2 * np.pi))
    W = np.outer(alpha, alpha) - cho_solve((L, True), np.eye(len(X)))  # alpha alpha^T - K^-1
    grad = np.empty_like(theta)
    for d in range(X.shape[1]):
        D2 = (X[:, d, None] - X[None, :, d]) ** 2 / ls[d] ** 2
        grad[d] = -0.5 * np.sum(W * Kse * D2)
    grad[-2] = -0.5 * np.sum(W * Kse)
    grad[-1] = -0.5 * sn * np.trace(W)
    return nlml, grad


def select_inducing(X: np.ndarray, m: int, seed: int) -> np.ndarray:
    """Indices of m rows: the row nearest each k-means centroid (Trivedi et al.'s cluster selection)."""
    rng = np.random.default_rng(seed)
    if len(X) <= m:
        return np.arange(len(X))
    sample = X[rng.choice(len(X), size=min(len(X), 20 * m), replace=False)]
    centroids, _ = kmeans2(sample, m, minit="++", seed=seed)
    idx = []
    for c in range(0, m, 256):
        block = centroids[c : c + 256]
        best = np.full(len(block), np.inf)
        arg = np.zeros(len(block), dtype=int)
        for r in range(0, len(X), CHUNK):
            d = np.sum((X[r : r + CHUNK, None, :] - block[None]) ** 2, -1)
            j = np.argmin(d, 0)
            better = d[j, np.arange(len(block))] < best
            best[better] = d[j, np.arange(len(block))][better]
            arg[better] = j[better] + r
        idx.extend(arg.tolist())
    return np.unique(np.array(idx))


class GPResidual(KinematicModel):
    name = "gp_residual"
    version = "1.0"
    required_columns = ("cmd_wl", "cmd_wr", "cmd_dwl", "cmd_dwr")
    calibrated_constants = ("wheel_radius",)
    DEFAULTS: dict[str, Any] = {
        "base": "edd",  # any installed model (its own options: base_options)
        "base_options": {},
        "n_inducing": 300,  # m: Trivedi et al. train on 500 cluster points; 300 keeps fit+predict < 30 s
        "standstill_speed": 0.01,  # m/s and rad/s: rows commanded below both are not trained on
        "max_opt_iter": 200,  # L-BFGS iterations of the marginal likelihood
        "seed": 0,
        "autocorr_lags_s": 10.0,
    }

    def __init__(self, robot, params=None, **options):
        unknown = sorted(set(options) - set(self.DEFAULTS))
        if unknown:
            known = sorted(self.DEFAULTS)
            raise ModelError(f"model {self.name}: unknown option(s) {unknown}; known: {known}")
        super().__init__(robot, params, **{**self.DEFAULTS, **options})
        if str(self.options["base"]) == self.name:
            raise ModelError(f"model {self.name}: options.base cannot be {self.name}")
        self._base: KinematicModel | None = None

    # -- the base model ------------------------------------------------------------------------
    def _base_class(self):
        return get_model_class(str(self.options["base"]))

    @property
    def base(self) -> KinematicModel:
        if self._base is None:
            saved = self.params.get("base")
            if not saved:
                raise ModelError(f"model {self.name}: not fitted")
            cls = self._base_class()
            self._base = cls.from_json(self.robot, saved) if hasattr(cls, "from_json") else cls(self.robot)
            base_arrays = {k[6:]: v for k, v in self.arrays.items() if k.startswith("base__")}
            if base_arrays:
                self._base.set_arrays(base_arrays)
        return self._base

    # -- fit -----------------------------------------------------------------------------------
    def fit(self, table: pd.DataFrame) -> GPResidual:
        with _one_blas_thread():
            return self._fit(table)

    def _fit(self, table: pd.DataFrame) -> GPResidual:
        self.check_columns(table, fitting=True)
        o = self.options
        base = self._base_class()(self.robot, **dict(o["base_options"] or {}))
        base.fit(table)
        self._base = base
        valid = table["valid"].to_numpy(bool)
        X = gp_features(table, self.robot)
        still = (np.abs(X[:, 0]) < o["standstill_speed"]) & (np.abs(X[:, 1]) < o["standstill_speed"])
        use = valid & ~still
        if use.sum() < 20:
            raise ModelError(f"model {self.name}: {int(use.sum())} moving valid training rows")
        resid = targets(table) - base.predict(table)
        Xu, R = X[use], resid[use]
        mu, sd = Xu.mean(0), Xu.std(0)
        sd[sd < 1e-9] = 1.0
        Xs = (Xu - mu) / sd
        idx = select_inducing(Xs, int(o["n_inducing"]), int(o["seed"]))
        Z = Xs[idx]
        arrays: dict[str, np.ndarray] = {"x_mean": mu, "x_scale": sd, "inducing": Z}
        hyper = []
        for j, name in enumerate(TARGETS):
            y = R[:, j]
            yz = y[idx]
            var0 = max(float(np.var(y)), 1e-10)
            theta0 = np.concatenate([np.zeros(Xs.shape[1]), [np.log(var0), np.log(0.1 * var0)]])
            res = minimize(
                neg_log_marginal, theta0, args=(Z, yz), method="L-BFGS-B", jac=True,
                bounds=[(-4, 4)] * Xs.shape[1] + [(np.log(var0) - 12, np.log(var0) + 4)] * 2,
                options={"maxiter": int(o["max_opt_iter"])},
            )  # fmt: skip
            theta = res.x
            ls, sf, sn = np.exp(theta[:-2]), float(np.exp(theta[-2])), float(np.exp(theta[-1]))
            sn = max(sn, 1e-10)
            Kmm = se_kernel(Z, Z, ls, sf) + 1e-6 * sf * np.eye(len(Z))
            Lmm = np.linalg.cholesky(Kmm)
            # whitened DTC (numerically stable for small noise): V = Lmm^-1 Kmn, B = I + V V^T / sn,
            # accumulated over row blocks; mean = q*^T B^-1 V y / sn with q* = Lmm^-1 k*
            B = np.eye(len(Z))
            c = np.zeros(len(Z))
            for r in range(0, len(Xs), CHUNK):
                V = solve_triangular(Lmm, se_kernel(Z, Xs[r : r + CHUNK], ls, sf), lower=True)
                B += V @ V.T / sn
                c += V @ y[r : r + CHUNK] / sn
            LB = np.linalg.cholesky(B)
            arrays[f"{name}_beta"] = cho_solve((LB, True), c)
            arrays[f"{name}_Lmm"] = Lmm
            arrays[f"{name}_LB"] = LB
            arrays[f"{name}_theta"] = theta
            hyper.append(
                {"lengthscales": ls.tolist(), "signal_var": sf, "noise_var": sn, "nlml": float(res.fun)}
            )
        for k, v in getattr(base, "arrays", {}).items():
            arrays[f"base__{k}"] = np.asarray(v)
        self.arrays = arrays
        self.params = {
            "base": base.to_json(),
            "features": list(FEATURE_NAMES),
            "hyperparameters": dict(zip(TARGETS, hyper, strict=True)),
            "n_inducing": len(Z),
            "n_train": int(use.sum()),
        }
        rows = table.loc[valid]
        res = targets(rows) - self.predict(rows)
        self.fit_loss_ = mse(self.predict(rows), targets(rows))
        dt = float(np.median(np.diff(col(table, "t")))) if len(table) > 1 else 1.0
        lags = max(1, int(round(float(o["autocorr_lags_s"]) / max(dt, 1e-6))))
        starts = sequence_starts(rows) | (np.diff(rows.index.to_numpy(), prepend=-2) != 1)
        self.arrays["error_autocorrelation"] = error_autocorrelation(res, starts, lags)
        return self

    @property
    def error_autocorrelation_(self) -> np.ndarray | None:
        return self.arrays.get("error_autocorrelation")

    # -- predict -------------------------------------------------------------------------------
    def _gp(self, table: pd.DataFrame, with_var: bool):
        with _one_blas_thread():
            return self._gp_blocks(table, with_var)

    def _gp_blocks(self, table: pd.DataFrame, with_var: bool):
        if "inducing" not in self.arrays:
            raise ModelError(f"model {self.name}: not fitted (no inducing points)")
        a = self.arrays
        Xs = (gp_features(table, self.robot) - a["x_mean"]) / a["x_scale"]
        Z = a["inducing"]
        mean = np.zeros((len(Xs), 3))
        var = np.zeros((len(Xs), 3))
        for j, name in enumerate(TARGETS):
            theta = a[f"{name}_theta"]
            ls, sf, sn = np.exp(theta[:-2]), float(np.exp(theta[-2])), max(float(np.exp(theta[-1])), 1e-10)
            for r in range(0, len(Xs), CHUNK):
                q = solve_triangular(a[f"{name}_Lmm"], se_kernel(Z, Xs[r : r + CHUNK], ls, sf), lower=True)
                mean[r : r + CHUNK, j] = q.T @ a[f"{name}_beta"]
                if with_var:
                    s = solve_triangular(a[f"{name}_LB"], q, lower=True)
                    var[r : r + CHUNK, j] = sn + sf - np.sum(q**2, 0) + np.sum(s**2, 0)
        return mean, np.maximum(var, 1e-12)

    def predict(self, table: pd.DataFrame) -> np.ndarray:
        self.check_columns(table)
        mean, _ = self._gp(table, with_var=False)
        return self.base.predict(table) + mean

    def predict_cov(self, table: pd.DataFrame) -> np.ndarray:
        """(T, 3, 3) diagonal predictive covariance of (vx, vy, wz): one GP per component."""
        self.check_columns(table)
        _, var = self._gp(table, with_var=True)
        cov = np.zeros((len(table), 3, 3))
        for j in range(3):
            cov[:, j, j] = var[:, j]
        return cov

    def set_arrays(self, arrays: dict[str, np.ndarray]) -> None:
        super().set_arrays(arrays)
        self._base = None
