"""The coverage study behind benchmark/scoring/intervals.py's choice of interval (docs/intervals.md): the
fraction of
95 % intervals of an RMSRE that hold its true value, per method, number of blocks and error correlation.

    .venv/bin/python tests/intervals_study.py [--reps 300]

Windows start every 0.2 s, so a one-horizon (6 s) block holds 30 windows. Relative errors (in %) are
lognormal, exp(log 5 + 0.5 x), x standard normal and:

- ``white``: independent between windows;
- ``ar1``: AR(1) over windows with coefficient 0.9 (a correlation time of 2 s, a third of a block);
- ``overlap``: each window's x is the mean over its 6 s of a per-sample AR(1) (0.2 s steps, correlation
  time 3 s), as overlapping windows of one drive are: neighbours share most of their data.

Methods, from the same block resamples (2000): ``percentile``, ``bca`` (jackknife over blocks),
``bootstrap-t`` (each resample studentized by its block-influence standard error; the original's with the
covariance of adjacent blocks) and ``ours`` (:func:`skidbench.benchmark.scoring.intervals.estimate`: the
bootstrap
standard error of log RMSRE widened by the adjacent blocks' covariance, Student-t quantile with K-1
degrees of freedom); and the widths (hi - lo) / estimate of the last two, median and largest. Not a test:
it prints the table docs/intervals.md quotes.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.signal
import scipy.stats

from skidbench.benchmark.scoring import intervals as iv

H, SPACING = 6.0, 0.2
PER_BLOCK = int(round(H / SPACING))


def errors(rng, scenario: str, n: int) -> tuple[np.ndarray, float]:
    """(n,) relative errors in % and their true RMSRE."""
    a, s = np.log(5.0), 0.5
    if scenario == "white":
        x = rng.standard_normal(n)
    elif scenario == "ar1":
        x = _ar1(rng, n, 0.9)
    else:
        phi = np.exp(-SPACING / 3.0)
        z = _ar1(rng, n + PER_BLOCK, phi)
        c = np.concatenate([[0.0], np.cumsum(z)])
        m = (c[PER_BLOCK : PER_BLOCK + n] - c[:n]) / PER_BLOCK
        k = np.arange(1, PER_BLOCK)
        x = m / np.sqrt((PER_BLOCK + 2 * np.sum((PER_BLOCK - k) * phi**k)) / PER_BLOCK**2)
    return np.exp(a + s * x), float(np.exp(a + s**2))


def _ar1(rng, n: int, phi: float) -> np.ndarray:
    y = scipy.signal.lfilter([np.sqrt(1 - phi**2)], [1.0, -phi], rng.standard_normal(n))
    return y + phi ** np.arange(1, n + 1) * rng.standard_normal()


def one(
    rng, scenario: str, blocks: int, seed: int, mult: int = 1
) -> tuple[dict[str, bool], dict[str, float]]:
    """One repetition, ``blocks`` blocks of ``mult`` horizons each: whether each method's interval holds the
    true RMSRE, and the interval width relative to the estimate of ours and the bootstrap-t."""
    n = blocks * PER_BLOCK * mult
    e, true = errors(rng, scenario, n)
    t0 = np.arange(n) * SPACING
    sample = iv.Sample(iv.IntervalConfig(seed=seed, block_s=mult * H))
    st = sample.add("s", np.zeros(n, int), t0, {"m": e}, H)
    ours = iv.estimate(sample, [iv.cell("m", "s", "m")]).iloc[0]
    S, N = st.sums["m"]
    W = sample.weights("s")
    theta = np.sqrt(S.sum() / N.sum())
    boot = np.sqrt((W @ S) / (W @ N))
    out = {"ours": ours["lo"] <= true <= ours["hi"]}
    lo, hi = np.quantile(boot, [0.025, 0.975])
    out["percentile"] = lo <= true <= hi
    jack = np.sqrt((S.sum() - S) / (N.sum() - N))
    d = jack.mean() - jack
    acc = np.sum(d**3) / (6 * np.sum(d**2) ** 1.5)
    z0 = scipy.stats.norm.ppf(np.clip(np.mean(boot < theta), 1e-6, 1 - 1e-6))
    z = scipy.stats.norm.ppf([0.025, 0.975])
    adj = scipy.stats.norm.cdf(z0 + (z0 + z) / (1 - acc * (z0 + z)))
    lo, hi = np.quantile(boot, adj)
    out["bca"] = lo <= true <= hi
    m, mb = theta**2, boot**2
    u = (S - m * N) / (2 * theta * N.sum())
    ub = (S[None, :] - mb[:, None] * N[None, :]) / (2 * boot[:, None] * (W @ N)[:, None])
    f = blocks / (blocks - 1)
    cross = max(float(np.sum(u[:-1] * u[1:] * st.adjacent)), 0.0)
    se, se_b = np.sqrt(f * (np.sum(u**2) + 2 * cross)), np.sqrt(f * np.sum(W * ub**2, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.nan_to_num((boot - theta) / se_b, nan=0.0)
    q_hi, q_lo = np.quantile(t, [0.975, 0.025], method="inverted_cdf")
    out["bootstrap-t"] = theta - q_hi * se <= true <= theta - q_lo * se
    width = {"ours": (ours["hi"] - ours["lo"]) / theta, "bootstrap-t": (q_hi - q_lo) * se / theta}
    return out, width


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--reps", type=int, default=300)
    p.add_argument("--blocks", type=int, nargs="*", default=[4, 5, 8, 16, 32])
    p.add_argument("--horizons-per-block", type=int, default=1)
    p.add_argument("--errors", nargs="*", default=["white", "ar1", "overlap"])
    args = p.parse_args()
    methods = ("percentile", "bca", "bootstrap-t", "ours")
    se = np.sqrt(0.95 * 0.05 / args.reps)
    print(f"coverage of 95 % intervals over {args.reps} repetitions (binomial s.e. {se:.3f}), "
          f"blocks of {args.horizons_per_block} horizon(s)")  # fmt: skip
    print("| errors | blocks | " + " | ".join(methods) + " | width ours (median / max) | width bootstrap-t |")
    print("|---|---:|" + "---:|" * (len(methods) + 2))
    started = time.time()
    for scenario in args.errors:
        for blocks in args.blocks:
            rng = np.random.default_rng([blocks, len(scenario)])
            hits = {m: 0 for m in methods}
            widths: dict[str, list[float]] = {"ours": [], "bootstrap-t": []}
            for r in range(args.reps):
                covered, width = one(rng, scenario, blocks, r, args.horizons_per_block)
                for m, ok in covered.items():
                    hits[m] += bool(ok)
                for m, w in width.items():
                    widths[m].append(w)
            cells = " | ".join(f"{hits[m] / args.reps:.3f}" for m in methods)
            wide = " | ".join(f"{np.median(widths[m]):.2f} / {np.max(widths[m]):.1f}" for m in widths)
            print(f"| {scenario} | {blocks} | {cells} | {wide} |", flush=True)
    print(f"({time.time() - started:.0f} s)")


if __name__ == "__main__":
    main()
