"""Window errors of known dependence on the designs the boards use, for the coverage of the intervals
(benchmark/scoring/intervals.py): ``perf/coverage.py`` (``make bench BENCH=coverage``) measures it on every
design below, tests/test_evaluate_intervals.py on one of them with a fixed seed.

Windows start every 0.2 s (a 6 s horizon: 30 windows per window length). A window's relative error (%) is
lognormal, ``exp(log 5 + 0.5 x)`` (a median of 5 %, skewed as relative errors are), where ``x`` is the mean
over the window's 6 s of a per-sample process of unit variance (overlapping windows share their data):

- ``3s``: one component with a 3 s correlation time (AR(1) on 0.2 s steps);
- ``3s+30s``: 70 % of the variance with a 3 s and 30 % with a 30 s correlation time (a slow component a
  drive of 45-60 s barely shows);
- ``3s+drift``: the 3 s component plus a drift over each drive (a random slope: the error's level moves
  by +-0.25 standard deviations from the drive's middle to its ends, typically).

A design is a list of strata (a terrain's test split), each a list of its sequences' durations (s); the
statistic is the mean over strata of each stratum's RMSRE (a cell, a terrain's aggregate, the board's
mean over terrains). The true value: the mean over strata of sqrt(E e^2) averaged over the stratum's
windows (what another drive would give on average).
"""

from __future__ import annotations

import numpy as np
import scipy.signal

H, SPACING = 6.0, 0.2
PER_WINDOW = int(round(H / SPACING))

#: the boards' designs: mini's splits (CV 45 s, LD 60 s, one drive each) as a cell, a terrain's aggregate
#: and the mean over three terrains; a board of two drives per split; a split of eight drives
DESIGNS: dict[str, list[list[float]]] = {
    "cell, one 45 s drive": [[45.0]],
    "terrain, 45 s + 60 s": [[45.0], [60.0]],
    "3 terrains, 45 s + 60 s": [[45.0], [60.0]] * 3,
    "cell, 4 drives of 45 s": [[45.0] * 4],
    "3 terrains, 2 drives each": [[45.0, 45.0], [60.0, 60.0]] * 3,
    "cell, 8 drives of 45 s": [[45.0] * 8],
}
#: error processes: (variance share, correlation time s) per component, and the drift's size
ERRORS: dict[str, tuple[list[tuple[float, float]], float]] = {
    "3s": ([(1.0, 3.0)], 0.0),
    "3s+30s": ([(0.7, 3.0), (0.3, 30.0)], 0.0),
    "3s+drift": ([(1.0, 3.0)], 0.5),
}


def _ar(rng, n: int, tau: float) -> np.ndarray:
    """(n,) a stationary AR(1) of unit variance on SPACING steps with correlation time ``tau`` s."""
    phi = np.exp(-SPACING / tau)
    y = scipy.signal.lfilter([np.sqrt(1 - phi**2)], [1.0, -phi], rng.standard_normal(n))
    return y + phi ** np.arange(1, n + 1) * rng.standard_normal()


def _window_var(tau: float) -> float:
    """The variance of a window's mean of that AR(1)."""
    phi = np.exp(-SPACING / tau)
    k = np.arange(1, PER_WINDOW)
    return float((PER_WINDOW + 2 * np.sum((PER_WINDOW - k) * phi**k)) / PER_WINDOW**2)


def drive(rng, duration_s: float, errors: str) -> tuple[np.ndarray, np.ndarray]:
    """One drive's window values ``x`` (W,) and their variance (W,) (for the true value)."""
    components, drift = ERRORS[errors]
    n_win = int(round((duration_s - H) / SPACING))
    x, var = np.zeros(n_win), np.zeros(n_win)
    for share, tau in components:
        z = _ar(rng, n_win + PER_WINDOW - 1, tau)
        c = np.concatenate([[0.0], np.cumsum(z)])
        x += np.sqrt(share / _window_var(tau)) * (c[PER_WINDOW:] - c[:-PER_WINDOW])[:n_win] / PER_WINDOW
        var += share
    if drift:
        along = np.linspace(-0.5, 0.5, n_win)
        x += drift * rng.standard_normal() * along
        var = var + (drift * along) ** 2
    return x, var


def stratum(rng, durations, errors: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """``(sequence, t0, relative error %, true RMSRE)`` of one stratum of drives."""
    a, s = np.log(5.0), 0.5
    seqs, t0s, errs, true2 = [], [], [], []
    for i, d in enumerate(durations):
        x, var = drive(rng, d, errors)
        seqs += [f"s{i}"] * len(x)
        t0s.append(np.arange(len(x)) * SPACING)
        errs.append(np.exp(a + s * x))
        true2.append(np.exp(2 * a + 2 * s**2 * var))
    return (
        np.array(seqs),
        np.concatenate(t0s),
        np.concatenate(errs),
        float(np.sqrt(np.mean(np.concatenate(true2)))),
    )


def coverage(design: str, errors: str, reps: int, seed: int = 0, resamples: int = 999) -> dict[str, float]:
    """The fraction of ``reps`` intervals of the design's statistic that hold its true value, how often
    it was rankable, and the median width relative to the estimate."""
    from skidbench.benchmark.scoring import intervals as iv
    from skidbench.benchmark.scoring.settings import IntervalConfig

    rng = np.random.default_rng([seed, len(design), len(errors)])
    hits = ranked = 0
    widths = []
    for r in range(reps):
        strata = [stratum(rng, durations, errors) for durations in DESIGNS[design]]
        sample = iv.Sample(IntervalConfig(seed=seed * 100_003 + r, resamples=resamples))
        cells = []
        for i, (seq, t0, e, _) in enumerate(strata):
            sample.add(f"s{i}", seq, t0, {"m": e}, H)
            cells.append(iv.cell(f"c{i}", f"s{i}", "m"))
        row = iv.estimate(sample, [iv.mean_of("m", cells)]).iloc[0]
        truth = float(np.mean([st[3] for st in strata]))
        hits += bool(row["lo"] <= truth <= row["hi"])
        ranked += bool(row["rankable"])
        widths.append((row["hi"] - row["lo"]) / row["estimate"])
    return {"coverage": hits / reps, "rankable": ranked / reps, "width": float(np.median(widths))}
