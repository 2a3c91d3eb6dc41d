"""The figure data of discrepancy discovery (:mod:`skidbench.benchmark.discovery.discover`): per step, the
held-out residual binned against the signal that revealed the effect (or term), with the correction the
model added; and, when nothing more passes, the residual against its strongest correlates. Plotted by
``discover_app.figure``."""

from __future__ import annotations

import numpy as np

from skidbench.benchmark.discovery.stats import HeldOut
from skidbench.models.augmented import terms as termlib
from skidbench.models.augmented.effects import CATALOGUE, revealing_feature
from skidbench.models.augmented.fit import CHANNELS, Augmenter, FitState, Pool


def binned(x: np.ndarray, r: np.ndarray, extra: np.ndarray | None = None) -> dict[str, list[float]]:
    """Quantile-binned means (and standard errors) of ``r`` against ``x`` (20 bins)."""
    if len(x) < 10:
        return {}
    qs = np.unique(np.quantile(x, np.linspace(0, 1, 21)))
    if len(qs) < 2:
        return {}
    idx = np.clip(np.searchsorted(qs, x, side="right") - 1, 0, len(qs) - 2)
    nb = len(qs) - 1
    cnt = np.bincount(idx, minlength=nb).astype(float)
    ok = cnt > 0
    c = np.maximum(cnt, 1)

    def mean(y):
        return np.where(ok, np.bincount(idx, y, minlength=nb) / c, np.nan)

    by = mean(r)
    sd = np.sqrt(np.maximum(mean(r * r) - by**2, 0.0))
    out = {"bin_x": mean(x).tolist(), "bin_y": by.tolist(), "bin_se": (sd / np.sqrt(c)).tolist()}
    if extra is not None:
        out["bin_fit"] = mean(extra).tolist()
    return out


def term_panel(
    pool: Pool, state: FitState, term: termlib.Term, ho: HeldOut, after: FitState, aug: Augmenter
) -> dict:
    """Held-out residual of the term's (first) channel against its signal, and the correction added."""
    ch = 0 if term.channel < 0 else term.channel
    sig = aug.signals(state.feats, state.base_pred)
    x = sig["rim_l"] if term.family == "slip" and term.signal == "l" else None
    if x is None:
        x = sig["rim_r"] if term.family == "slip" else None
    if x is None:
        x = sig["t"] if term.family == "after" else None
    if x is None:
        x = np.maximum(np.abs(sig["rim_l"]), np.abs(sig["rim_r"])) if term.channel < 0 else None
    if x is None:
        x = termlib._signal(term.signal, sig)
    r = (pool.target - ho.pred)[:, ch]
    m = pool.valid & np.isfinite(x)
    out = {"effect": term.key, "channel": CHANNELS[ch], "feature": term.signal, "accepted": True}
    out.update(binned(x[m], r[m], (after.pred - state.pred)[:, ch][m]))
    return out


def unexplained_panels(pool: Pool, aug: Augmenter, state: FitState, ho: HeldOut, rep: dict) -> list[dict]:
    """One panel per velocity channel: the held-out residual against its strongest correlate."""
    sig = aug.signals(state.feats, state.base_pred)
    out = []
    for c, ch in enumerate(CHANNELS):
        if not rep["correlates"][ch]:
            continue
        name = rep["correlates"][ch][0]["signal"]
        x = termlib._signal(name, sig)
        r = (pool.target - ho.pred)[:, c]
        m = pool.valid & np.isfinite(x)
        d = {
            "effect": "unexplained",
            "channel": ch,
            "feature": f"{name} (r = {rep['correlates'][ch][0]['r']:+.2f})",
        }
        d.update(binned(x[m], r[m]))
        d["accepted"] = False
        d["unexplained"] = True
        out.append(d)
    return out


def residual_panel(pool: Pool, state: FitState, eid: str | None, ho: HeldOut, after: FitState | None) -> dict:
    """Binned held-out residual of the effect's channel against the feature that revealed it."""
    if eid is None:
        return {}
    e = CATALOGUE[eid]
    ch = 2 if e.channel < 0 else e.channel
    x = revealing_feature(eid, state.feats, state.base_pred)
    r = (pool.target - ho.pred)[:, ch]
    m = pool.valid & np.isfinite(x)
    x, r = x[m], r[m]
    out = {"effect": eid, "channel": CHANNELS[ch], "feature": e.feature_label, "accepted": after is not None}
    if len(x) < 10:
        return out
    qs = np.unique(np.quantile(x, np.linspace(0, 1, 21)))
    idx = np.clip(np.searchsorted(qs, x, side="right") - 1, 0, len(qs) - 2)
    bx = np.array([x[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(qs) - 1)])
    by = np.array([r[idx == i].mean() if np.any(idx == i) else np.nan for i in range(len(qs) - 1)])
    be = np.array(
        [
            r[idx == i].std() / max(1, np.sum(idx == i)) ** 0.5 if np.any(idx == i) else np.nan
            for i in range(len(qs) - 1)
        ]
    )
    out.update({"bin_x": bx.tolist(), "bin_y": by.tolist(), "bin_se": be.tolist()})
    if after is not None:  # the correction the effect adds (relative to the previous model), binned
        delta = (after.pred - state.pred)[:, ch][m]
        out["bin_fit"] = [
            float(delta[idx == i].mean()) if np.any(idx == i) else float("nan") for i in range(len(qs) - 1)
        ]
    return out
