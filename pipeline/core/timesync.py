"""Time association: the one home for putting samples of one clock on the times of another.

Every function takes integer nanosecond stamps (int64, sorted ascending where it says so) and works on
whole arrays:

- :func:`nearest`: the nearest reference stamp within a tolerance (ORB-SLAM poses to image stamps,
  left/right stereo images); a tie goes to the earlier reference stamp.
- :func:`hold`: zero-order hold, the last sample at or before each time, zero before the first sample
  and after a timeout (commands, as a robot's controller applies them).
- :func:`bracket`: the pair of samples around each time, the interpolation fraction, and whether the
  interpolation is trusted: inside the coverage (no extrapolation) and between samples at most
  ``max_gap_ns`` apart. One rule, two readings of a time that falls exactly on a sample: a TF edge
  (``trust_samples=True``) takes the sample as exact whatever the gap beside it; the split's uniform
  grid (``trust_samples=False``) also asks the interval that starts at the sample to be short (the last
  sample is always exact).
- :func:`interp_with_gaps`: linear interpolation of values and the :func:`bracket` mask, minus gap
  intervals (ground truth and encoders on the split's grid).
- :func:`interp_se2`: (x, y, yaw) poses at other times, the yaw unwrapped before interpolating.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

__all__ = ["nearest", "hold", "bracket", "interp_with_gaps", "interp_se2"]


def nearest(stamps_ns: np.ndarray, ref_ns: np.ndarray, max_diff_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Nearest reference stamp for each stamp: ``(index into ref_ns (N,), matched (N,) bool)``.

    ``ref_ns`` (M,) sorted ascending, M >= 1; ``matched`` is ``|ref_ns[index] - stamp| <= max_diff_ns``.
    A stamp equally far from two reference stamps takes the earlier one."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    ref_ns = np.asarray(ref_ns, dtype=np.int64)
    if len(ref_ns) > 1:
        i = np.clip(np.searchsorted(ref_ns, stamps_ns), 1, len(ref_ns) - 1)
        left_closer = np.abs(stamps_ns - ref_ns[i - 1]) <= np.abs(ref_ns[i] - stamps_ns)
        i = np.where(left_closer, i - 1, i)
    else:
        i = np.zeros(len(stamps_ns), dtype=np.int64)
    return i, np.abs(ref_ns[i] - stamps_ns) <= max_diff_ns


def hold(
    stamps_ns: np.ndarray, values: np.ndarray, grid_ns: np.ndarray, timeout_ns: int | None
) -> np.ndarray:
    """Zero-order hold of ``values`` (N, k) sampled at ``stamps_ns`` (N,) at the times ``grid_ns`` (T,):
    (T, k), each row the last sample at or before its time; zero before the first sample and where that
    sample is more than ``timeout_ns`` old (None: never stale)."""
    values = np.asarray(values, dtype=float).reshape(len(stamps_ns), -1)
    i = np.searchsorted(stamps_ns, grid_ns, side="right") - 1
    out = values[np.clip(i, 0, None)].copy()
    stale = i < 0
    if timeout_ns is not None:
        stale |= grid_ns - stamps_ns[np.clip(i, 0, None)] > timeout_ns
    out[stale] = 0.0
    return out


def bracket(
    stamps_ns: np.ndarray, t_ns: np.ndarray, max_gap_ns: int, trust_samples: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The samples around each time ``t_ns`` (T,) among ``stamps_ns`` (M,) (sorted ascending):
    ``(i (T,), frac (T,), valid (T,))``.

    The time lies between ``stamps_ns[i]`` and ``stamps_ns[i + 1]`` at fraction ``frac`` in [0, 1]
    (M == 1: ``i`` = 0, ``frac`` = 0). ``valid``: inside ``[stamps_ns[0], stamps_ns[-1]]`` (never an
    extrapolation) and the two samples at most ``max_gap_ns`` apart; a time exactly on a sample is valid
    whatever the gap when ``trust_samples`` (else only the last sample is: module docstring)."""
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    t = np.asarray(t_ns, dtype=np.int64)
    if len(stamps_ns) == 1:
        zeros = np.zeros(len(t), dtype=np.int64)
        return zeros, zeros.astype(float), t == stamps_ns[0]
    i = np.clip(np.searchsorted(stamps_ns, t, side="right") - 1, 0, len(stamps_ns) - 2)
    span = stamps_ns[i + 1] - stamps_ns[i]
    offset = t - stamps_ns[i]
    # int64 differences: exact before the division; a repeated stamp (span 0) has fraction 0
    frac = np.clip(np.divide(offset, span, out=np.zeros(len(t)), where=span > 0), 0.0, 1.0)
    short = span <= max_gap_ns
    if trust_samples:
        short |= (offset == 0) | (offset == span)
    else:
        short |= t == stamps_ns[-1]
    valid = (t >= stamps_ns[0]) & (t <= stamps_ns[-1]) & short
    return i, frac, valid


def interp_with_gaps(
    stamps_ns: np.ndarray,
    values: np.ndarray,
    grid_ns: np.ndarray,
    max_gap_ns: int,
    gaps: Iterable[tuple[int, int]] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``values`` (N, k) sampled at ``stamps_ns`` (N,) at ``grid_ns`` (T,):
    ``(values (T, k), trusted (T,))``. Trusted: :func:`bracket` with ``trust_samples=False`` and not
    strictly inside any ``gaps`` interval ``(start_ns, end_ns)``. Untrusted rows hold np.interp's value
    (the end sample outside the coverage)."""
    values = np.asarray(values, dtype=float).reshape(len(stamps_ns), -1)
    t = (stamps_ns - stamps_ns[0]).astype(float)
    g = (grid_ns - stamps_ns[0]).astype(float)
    out = np.column_stack([np.interp(g, t, values[:, c]) for c in range(values.shape[1])])
    _, _, ok = bracket(stamps_ns, grid_ns, max_gap_ns, trust_samples=False)
    for a, b in gaps:
        ok &= ~((grid_ns > a) & (grid_ns < b))
    return out, ok


def interp_se2(t_ref: np.ndarray, se2: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses ``se2`` (M, 3) = (x, y, yaw) at times ``t_ref`` (M,) linearly interpolated at ``t`` (T,):
    (T, 3), yaw unwrapped first (cumulative, so a turn through +-pi interpolates the short way). Times
    in any one unit (floats); outside ``t_ref`` the end poses are held."""
    yaw = np.unwrap(se2[:, 2])
    return np.column_stack(
        [np.interp(t, t_ref, se2[:, 0]), np.interp(t, t_ref, se2[:, 1]), np.interp(t, t_ref, yaw)]
    )
