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

Version 2, so that the correction is only as large as held-out data support it (:func:`blocked_cv_select`):
the Train rows are cut into ``cv_folds`` contiguous time blocks; length scales (x ``cv_lengthscale_factors``
of the maximum-likelihood ones) and noise (x ``cv_noise_factors``) are chosen by the blocked
cross-validated MSE, since the marginal likelihood assumes white noise where a drive's residuals are
correlated over seconds; the mean is then multiplied by the held-out least-squares factor in [0, 1]
(``shrink``: 0 makes the model its base when the correction does not carry over to unseen blocks), the
predictive variance by held-out squared error / held-out predictive variance (``calibrate_variance``), and
the error autocorrelation the horizon integrates is that of the held-out errors. The vx GP
(``regime_outputs``) has a fifth input (``regime_tau_s``, default 1 s), the recent wheel acceleration
(:func:`recent_wheel_acceleration`): how hard the robot has been driven lately, which the command-to-velocity
lag and the base model's error depend on; a drive far gentler than Train's lies away from Train's inputs in
it, where the GP's mean decays to 0 (the base). Version 2.1: every output's GP trains on each Train row and
its left-right mirror image (``mirror_outputs``; a symmetric robot's prior: vy and wz odd in the turn, vx
even), so that a Train drive coupling speed and turn direction does not become a wz correction of the turns
it lacks. Version 1 is ``cv_folds=0 regime_tau_s=0 mirror_outputs=[]``.
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import pandas as pd
from scipy.cluster.vq import kmeans2
from scipy.linalg import cho_solve, solve_triangular
from scipy.optimize import minimize
from scipy.signal import lfilter

from skidbench.models.base import KinematicModel, ModelError
from skidbench.models.columns import TARGETS, col, error_autocorrelation, mse, sequence_starts, targets
from skidbench.models.registry.specs import get_model_class

try:  # installed with scipy's and scikit-learn's stacks; optional here
    from threadpoolctl import threadpool_limits
except ImportError:  # pragma: no cover
    threadpool_limits = None

FEATURE_NAMES = ("cmd_v", "cmd_w", "cmd_dv", "cmd_dw")
# the left-right mirror image of a drive (left and right wheels swapped): the GP inputs (cmd_v, cmd_w, dv,
# dw, recent wheel acceleration) become (v, -w, dv, -dw, same), the residual (vx, vy, wz) (vx, -vy, -wz)
MIRROR_INPUTS = np.array([1.0, -1.0, 1.0, -1.0, 1.0])
MIRROR_TARGETS = np.array([1.0, -1.0, -1.0])


def _one_blas_thread():
    """The GP's BLAS calls are on m x m and m x 8192 blocks, where a multi-threaded BLAS on a shared
    2-core machine spends more time handing work between threads than computing (measured: a 48k-row fit
    42 s with OpenBLAS's default threads, 3.6 s with one)."""
    return threadpool_limits(1, "blas") if threadpool_limits is not None else contextlib.nullcontext()


CHUNK = 8192  # rows per block of the O(N m^2) accumulation: bounded memory


def recent_wheel_acceleration(table: pd.DataFrame, tau_s: float) -> np.ndarray:
    """(T,) rad/s^2: root of the exponential moving average, time constant ``tau_s`` (s), of the protocol's
    squared wheel accelerations (mean of left and right), causal, restarted at each sequence: how hard the
    robot has been driven over the last few seconds (high in aggressive driving, ~0 when cruising)."""
    a2 = 0.5 * (col(table, "cmd_dwl") ** 2 + col(table, "cmd_dwr") ** 2)
    a2 = np.where(np.isfinite(a2), a2, 0.0)
    t = col(table, "t")
    starts = np.flatnonzero(sequence_starts(table)).tolist() + [len(table)]
    out = np.empty(len(table))
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        dt = float(np.median(np.diff(t[a:b]))) if b - a > 1 else 1.0
        k = 1.0 - np.exp(-max(dt, 1e-6) / tau_s)
        out[a:b], _ = lfilter([k], [1.0, k - 1.0], a2[a:b], zi=[(1.0 - k) * a2[a]])
    return np.sqrt(np.maximum(out, 0.0))


def gp_features(table: pd.DataFrame, robot, regime_tau_s: float = 0.0) -> np.ndarray:
    """(T, 4) GP inputs: commanded body velocity (m/s, rad/s) and acceleration (m/s^2, rad/s^2) of the
    protocol's wheel rates; (T, 5) with :func:`recent_wheel_acceleration` (rad/s^2) when regime_tau_s > 0."""
    v, w = robot.twist_from_wheel_rates(col(table, "cmd_wl"), col(table, "cmd_wr"))
    dv, dw = robot.twist_from_wheel_rates(col(table, "cmd_dwl"), col(table, "cmd_dwr"))
    if regime_tau_s > 0:
        return np.column_stack([v, w, dv, dw, recent_wheel_acceleration(table, regime_tau_s)])
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


def block_folds(table: pd.DataFrame, use: np.ndarray, k: int) -> np.ndarray | None:
    """(use.sum(),) fold index 0..k-1 of every training row: k contiguous blocks of the Train rows in time
    order (sequence after sequence), equal in row count. None when k < 2 (no cross-validation). Blocks, not
    random rows: the residuals are autocorrelated over seconds, so a randomly held-out row has its
    neighbours in the training folds and a held-out error would be that of interpolation, not of a new
    drive."""
    n = int(use.sum())
    if k < 2 or n < 10 * k:
        return None
    return np.minimum(np.arange(n) * k // n, k - 1)


def blocked_cv_select(
    Xs: np.ndarray,
    y: np.ndarray,
    Z: np.ndarray,
    ls: np.ndarray,
    sf: float,
    sn: float,
    folds: np.ndarray | None,
    ls_factors: list[float],
    noise_factors: list[float],
) -> dict[str, Any]:
    """Hyperparameters of one output by blocked cross-validation, and how far to trust the GP there.

    Xs (N, D) standardised inputs, y (N,) residuals of the base, Z (m, D) inducing inputs; ls, sf, sn the
    maximum-likelihood length scales, signal and noise variance. Candidates: length scales x ls_factors
    and noise x noise_factors (the marginal likelihood assumes white noise; the residuals are correlated
    over seconds, so it picks length scales and noise that interpolate the Train drive). Each candidate's
    DTC posterior is refitted without each block (the block's V V^T and V y subtracted from the totals:
    one pass over the rows per length scale) and predicts the held-out block. The candidate with the least
    held-out MSE is kept, then:
    - shrink: the factor in [0, 1] on its mean that minimises the held-out MSE (least squares of y on
      the held-out mean): 0 when the correction does not carry over to new blocks (the model is its base),
      1 when it does fully;
    - var_scale: mean held-out squared error / mean held-out predictive variance, so the predictive
      variance matches the errors on data the fit did not see (mean z^2 = 1).
    Returns those, the chosen lengthscales and noise_var, Lmm, G = V V^T and h = V y over all rows (for the
    final posterior), the held-out means (N,) ('heldout', None without folds) and the held-out MSE of the
    candidate (cv_mse) and of the base (cv_mse_base: the residual itself)."""
    out: dict[str, Any] = {"lengthscale_factor": 1.0, "noise_factor": 1.0, "shrink": 1.0, "var_scale": 1.0}
    out.update(heldout=None, cv_mse=None, cv_mse_base=float(np.mean(y**2)))
    if folds is None:
        ls_factors, noise_factors = [1.0], [1.0]
    k = 0 if folds is None else int(folds.max()) + 1
    m = len(Z)
    best = None
    for a in ls_factors:
        lsa = ls * a
        Lmm = np.linalg.cholesky(se_kernel(Z, Z, lsa, sf) + 1e-6 * sf * np.eye(m))
        V = np.empty((m, len(Xs)))
        for r in range(0, len(Xs), CHUNK):
            V[:, r : r + CHUNK] = solve_triangular(Lmm, se_kernel(Z, Xs[r : r + CHUNK], lsa, sf), lower=True)
        Gk = [V[:, folds == f] @ V[:, folds == f].T for f in range(k)]
        hk = [V[:, folds == f] @ y[folds == f] for f in range(k)]
        G = sum(Gk) if k else V @ V.T
        h = sum(hk) if k else V @ y
        for b in noise_factors:
            s2 = sn * b
            if b != noise_factors[0] and s2 > 2.0 * np.mean(y**2):
                continue
            pred = np.zeros(len(y))
            for f in range(k):
                L = np.linalg.cholesky(np.eye(m) + (G - Gk[f]) / s2)
                pred[folds == f] = V[:, folds == f].T @ cho_solve((L, True), (h - hk[f]) / s2)
            err = float(np.mean((y - pred) ** 2)) if k else 0.0
            if best is None or err < best[0]:
                best = (err, a, b, lsa, s2, Lmm, G, h, Gk, hk, V, pred)
    err, a, b, lsa, s2, Lmm, G, h, Gk, hk, V, pred = best
    out.update(lengthscale_factor=a, noise_factor=b, lengthscales=lsa, noise_var=s2, Lmm=Lmm, G=G, h=h)
    if not k:
        return out
    pp = float(pred @ pred)
    alpha = float(np.clip(y @ pred / pp, 0.0, 1.0)) if pp > 0 else 0.0
    var = np.zeros(len(y))
    for f in range(k):
        L = np.linalg.cholesky(np.eye(m) + (G - Gk[f]) / s2)
        q = V[:, folds == f]
        var[folds == f] = s2 + sf - np.sum(q**2, 0) + np.sum(solve_triangular(L, q, lower=True) ** 2, 0)
    r = y - alpha * pred
    out.update(shrink=alpha, var_scale=float(np.mean(r**2) / max(np.mean(var), 1e-300)))
    out.update(heldout=pred, cv_mse=err)
    return out


def input_dims(name: str, n_inputs: int, regime_outputs) -> list[int]:
    """Columns of the GP inputs the output ``name`` uses: all of them if it is among ``regime_outputs``,
    else the first four (commanded velocity and acceleration, without the recent wheel acceleration)."""
    return list(range(n_inputs)) if name in list(regime_outputs or []) else list(range(min(n_inputs, 4)))


class GPResidual(KinematicModel):
    name = "gp_residual"
    version = "2.1"
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
        # blocked cross-validation on Train (contiguous time blocks; 0 or 1: maximum likelihood only)
        "cv_folds": 5,
        "cv_lengthscale_factors": [1.0, 2.0, 4.0, 8.0],  # x the maximum-likelihood length scales
        # x the maximum-likelihood noise variance, those up to the residual's variance (the likelihood on
        # the spread-out inducing rows cannot tell noise from signal and often picks a far too small noise)
        "cv_noise_factors": [1.0, 4.0, 16.0, 64.0, 256.0, 1024.0, 4096.0],
        "shrink": True,  # scale the mean by the held-out least-squares factor in [0, 1]
        "calibrate_variance": True,  # scale the predictive variance to the held-out squared errors
        "autocorr_residuals": "heldout",  # "heldout" (blocked CV) or "fit" (in-sample) errors
        "regime_tau_s": 1.0,  # s; > 0: a fifth input, the recent wheel acceleration (0: none)
        "regime_outputs": ["vx"],  # the outputs whose GP gets that fifth input (measured: see docs/models.md)
        # the outputs whose GP trains on every row and its left-right mirror image (a symmetric robot's prior)
        "mirror_outputs": ["vx", "vy", "wz"],
    }

    def __init__(self, robot, params=None, **options):
        super().__init__(robot, params, **options)  # DEFAULTS: checked and applied there
        if self.options["autocorr_residuals"] not in ("heldout", "fit"):
            raise ModelError(f"model {self.name}: options.autocorr_residuals must be 'heldout' or 'fit'")
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
        """The base model, then per output a sparse GP on its residuals over the moving valid rows
        (standardised features, shared inducing points), then the residuals' autocorrelation."""
        o = self.options
        self.check_columns(table, fitting=True)
        base = self._base_class()(self.robot, **dict(o["base_options"] or {}))
        base.fit(table)
        self._base = base
        use, Xu, R, folds = self._residual_rows(table, base)
        n_use = len(Xu)
        mirror = list(o["mirror_outputs"] or [])
        if mirror:
            # a skid-steer robot is left-right symmetric: the residual of a mirrored drive is the mirrored
            # residual, so vy and wz are odd in (w, dw) and vx even. Without it the GP transfers Train's
            # correction of, e.g., its hard forward right turns to straight or left-turning driving Train
            # lacks (Train's forward rows turning one way, its reverse rows the other): on the DRIVE
            # Warthog's LD that was a +0.086 rad/s wz bias on gently turning forward windows (docs/models.md).
            Xu = np.vstack([Xu, Xu * MIRROR_INPUTS[: Xu.shape[1]]])
            R = np.vstack([R, R * MIRROR_TARGETS])
            folds = None if folds is None else np.concatenate([folds, folds])  # a row and its mirror together
        mu, sd = Xu.mean(0), Xu.std(0)
        sd[sd < 1e-9] = 1.0
        Xs = (Xu - mu) / sd
        idx = select_inducing(Xs, int(o["n_inducing"]), int(o["seed"]))
        arrays: dict[str, np.ndarray] = {"x_mean": mu, "x_scale": sd, "inducing": Xs[idx]}
        hyper = []
        heldout = np.full((len(table), 3), np.nan)  # held-out residuals of the blocked CV (used rows)
        for j, name in enumerate(TARGETS):
            rows = slice(None) if name in mirror else slice(0, n_use)  # the mirror images are rows n_use..
            iz = idx if name in mirror else idx[idx < n_use]  # the likelihood's rows: inducing rows fitted
            fold = None if folds is None else folds[rows]
            out, h, cv_heldout = self._fit_output(name, Xs[rows], R[rows, j], Xs[iz], R[iz, j], Xs[idx], fold)
            arrays.update(out)
            hyper.append(h)
            if cv_heldout is not None:
                heldout[np.flatnonzero(use), j] = cv_heldout[:n_use]
        for k, v in getattr(base, "arrays", {}).items():
            arrays[f"base__{k}"] = np.asarray(v)
        self.arrays = arrays
        self.params = {
            "base": base.to_json(),
            "features": list(FEATURE_NAMES) + (["wheel_acc_rms"] if float(o["regime_tau_s"]) > 0 else []),
            "regime_tau_s": float(o["regime_tau_s"]),
            "hyperparameters": dict(zip(TARGETS, hyper, strict=True)),
            "n_inducing": len(idx),
            "n_train": int(use.sum()),
        }
        self._fit_residual_autocorrelation(table, heldout)
        return self

    def _residual_rows(self, table: pd.DataFrame, base: KinematicModel):
        """(the rows the GP is trained on: valid and moving, their features, the base model's residuals
        there, their blocked CV folds or None)."""
        o = self.options
        valid = table["valid"].to_numpy(bool)
        X = gp_features(table, self.robot, float(o["regime_tau_s"]))
        still = (np.abs(X[:, 0]) < o["standstill_speed"]) & (np.abs(X[:, 1]) < o["standstill_speed"])
        use = valid & ~still
        if use.sum() < 20:
            raise ModelError(f"model {self.name}: {int(use.sum())} moving valid training rows")
        resid = targets(table) - base.predict(table)
        return use, X[use], resid[use], block_folds(table, use, int(o["cv_folds"]))

    def _fit_output(self, name: str, Xs, y, Xs_z, y_z, Z, folds):
        """One output's GP: the hyperparameters maximising the marginal likelihood on the inducing rows
        (``Xs_z``, ``y_z``), then the blocked CV's scale factors, shrink and variance scale on the rows
        ``Xs``, ``y`` (standardised features, every input). Returns (its arrays, its hyperparameters' record,
        its held-out residuals or None)."""
        o = self.options
        dims = input_dims(name, Xs.shape[1], o["regime_outputs"])
        Xj, Zj = Xs[:, dims], Z[:, dims]
        var0 = max(float(np.var(y)), 1e-10)
        theta0 = np.concatenate([np.zeros(len(dims)), [np.log(var0), np.log(0.1 * var0)]])
        res = minimize(
            neg_log_marginal, theta0, args=(Xs_z[:, dims], y_z), method="L-BFGS-B", jac=True,
            bounds=[(-4, 4)] * len(dims) + [(np.log(var0) - 12, np.log(var0) + 4)] * 2,
            options={"maxiter": int(o["max_opt_iter"])},
        )  # fmt: skip
        theta = res.x
        ls, sf, sn = np.exp(theta[:-2]), float(np.exp(theta[-2])), float(np.exp(theta[-1]))
        sn = max(sn, 1e-10)
        sel = blocked_cv_select(
            Xj, y, Zj, ls, sf, sn, folds,
            [float(a) for a in o["cv_lengthscale_factors"]], [float(b) for b in o["cv_noise_factors"]],
        )  # fmt: skip
        ls, sn, Lmm, G, h = sel["lengthscales"], sel["noise_var"], sel["Lmm"], sel["G"], sel["h"]
        alpha = sel["shrink"] if o["shrink"] else 1.0
        kappa = sel["var_scale"] if o["calibrate_variance"] else 1.0
        heldout = None if sel["heldout"] is None else y - alpha * sel["heldout"]
        # whitened DTC (numerically stable for small noise): V = Lmm^-1 Kmn, B = I + V V^T / sn,
        # mean = q*^T B^-1 V y / sn with q* = Lmm^-1 k*; G = V V^T and h = V y over all rows
        LB = np.linalg.cholesky(np.eye(len(Z)) + G / sn)
        arrays = {
            f"{name}_beta": alpha * cho_solve((LB, True), h / sn),
            f"{name}_Lmm": Lmm,
            f"{name}_LB": LB,
            f"{name}_theta": np.concatenate([np.log(ls), [np.log(sf), np.log(sn)]]),
            f"{name}_var_scale": np.array(kappa),
        }
        if o["calibrate_variance"] and alpha == 0.0 and sel["heldout"] is not None:
            # no correction carries over: the output is its base's, and so is its variance, the base's
            # held-out squared residual everywhere (the unshrunk GP's shape of it is not the base's:
            # with it, a residual that is white noise had wz intervals covering 92 %, not 95 %)
            arrays[f"{name}_var_const"] = np.array(float(np.mean(y**2)))
        arrays[f"{name}_dims"] = np.array(dims)
        hyper = {
            "lengthscales": ls.tolist(), "signal_var": sf, "noise_var": sn, "nlml": float(res.fun),
            "lengthscale_factor": sel["lengthscale_factor"], "noise_factor": sel["noise_factor"],
            "shrink": float(alpha), "var_scale": float(kappa),
            "cv_mse": sel["cv_mse"], "cv_mse_base": sel["cv_mse_base"],
        }  # fmt: skip
        return arrays, hyper, heldout

    def _fit_residual_autocorrelation(self, table: pd.DataFrame, heldout: np.ndarray) -> None:
        """The fit loss and the autocorrelation of the fitted model's errors on the valid Train rows (the
        blocked CV's held-out errors where it has them, with ``autocorr_residuals=heldout``)."""
        o = self.options
        valid = table["valid"].to_numpy(bool)
        rows = table.loc[valid]
        pred = self.predict(table)
        res = targets(table) - pred
        if o["autocorr_residuals"] == "heldout":  # the errors the model makes on rows it did not see
            res = np.where(np.isnan(heldout), res, heldout)
        res = res[valid]
        self.fit_loss_ = mse(pred[valid], targets(rows))
        dt = float(np.median(np.diff(col(table, "t")))) if len(table) > 1 else 1.0
        lags = max(1, int(round(float(o["autocorr_lags_s"]) / max(dt, 1e-6))))
        starts = sequence_starts(rows) | (np.diff(rows.index.to_numpy(), prepend=-2) != 1)
        self.arrays["error_autocorrelation"] = error_autocorrelation(res, starts, lags)

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
        tau = float(self.params.get("regime_tau_s", 0.0))
        Xs = (gp_features(table, self.robot, tau) - a["x_mean"]) / a["x_scale"]
        Z = a["inducing"]
        mean = np.zeros((len(Xs), 3))
        var = np.zeros((len(Xs), 3))
        for j, name in enumerate(TARGETS):
            theta = a[f"{name}_theta"]
            ls, sf, sn = np.exp(theta[:-2]), float(np.exp(theta[-2])), max(float(np.exp(theta[-1])), 1e-10)
            dims = a.get(f"{name}_dims", np.arange(Xs.shape[1]))
            Xj, Zj = Xs[:, dims], Z[:, dims]
            for r in range(0, len(Xj), CHUNK):
                q = solve_triangular(a[f"{name}_Lmm"], se_kernel(Zj, Xj[r : r + CHUNK], ls, sf), lower=True)
                mean[r : r + CHUNK, j] = q.T @ a[f"{name}_beta"]
                if with_var:
                    s = solve_triangular(a[f"{name}_LB"], q, lower=True)
                    var[r : r + CHUNK, j] = sn + sf - np.sum(q**2, 0) + np.sum(s**2, 0)
            var[:, j] *= float(a.get(f"{name}_var_scale", 1.0))
            if f"{name}_var_const" in a:
                var[:, j] = float(a[f"{name}_var_const"])
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
