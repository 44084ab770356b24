"""The paper's tracking metrics, eqs. (64)-(65), as pure array functions.

e_k = ||e_p(t_k)||; mean = (1/N) sum e_k; RMSE = sqrt((1/N) sum e_k^2); max = max e_k,
over the full run and over the steady-state window t >= steady_start (10 s in the paper).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["METRIC_KEYS", "true_reference_body", "tracking_metrics", "window_metrics", "batch_tracking_metrics",
           "history_metrics", "history_metrics_into", "steady_index"]

#: keys of :func:`tracking_metrics`, in table order
METRIC_KEYS: tuple[str, ...] = (
    "full_mean", "full_rmse", "full_max", "steady_mean", "steady_rmse", "steady_max")


def true_reference_body(info: dict) -> tuple[np.ndarray, np.ndarray]:
    """The true present reference point relative to the follower, in the follower's body frame
    (dx forward, dy to port) [m], from a vector env's ``info`` (``true_reference`` and
    ``follower_pose``, (N, 3) each): privileged, for training targets and scoring only."""
    ref, pose = info["true_reference"], info["follower_pose"]
    dx, dy = ref[:, 0] - pose[:, 0], ref[:, 1] - pose[:, 1]
    c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    return c * dx + s * dy, -s * dx + c * dy


def window_metrics(errors: np.ndarray) -> tuple[float, float, float]:
    """(mean, RMSE, max) of a 1-D error series; NaNs if it is empty."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return float("nan"), float("nan"), float("nan")
    return float(e.mean()), float(np.sqrt(np.mean(e * e))), float(e.max())


def tracking_metrics(errors: np.ndarray, times: np.ndarray, steady_start: float = 10.0) -> dict[str, float]:
    """Eq. (65) over the full run and over t >= ``steady_start``.

    Args:
        errors: tracking-error samples e_k [m], shape (N,).
        times: their times t_k [s], shape (N,).
        steady_start: first time of the steady-state window [s].

    Returns:
        dict with :data:`METRIC_KEYS`; a window without samples gives NaN.

    Raises:
        ValueError: if the arrays are not 1-D of equal length.
    """
    e = np.asarray(errors, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if e.ndim != 1 or t.shape != e.shape:
        raise ValueError(f"errors and times must be 1-D of equal length, got shapes {e.shape} "
                         f"and {t.shape}")
    full = window_metrics(e)
    steady = window_metrics(e[t >= steady_start - 1e-9])
    return dict(zip(METRIC_KEYS, full + steady, strict=False))


def batch_tracking_metrics(errors: np.ndarray, times: np.ndarray, steady_start: float = 10.0) -> dict[str, np.ndarray]:
    """:func:`tracking_metrics` of several episodes of one length at once.

    Args:
        errors: (E, N) error samples [m], one episode per row.
        times: their common times (N,) [s], increasing.
        steady_start: first time of the steady-state window [s].

    Returns:
        dict with :data:`METRIC_KEYS` of (E,) arrays, each entry equal to
        ``tracking_metrics(errors[j], times, steady_start)`` (numpy reduces each contiguous row
        as it reduces a 1-D array: the same pairwise sums).
    """
    e = np.ascontiguousarray(errors, dtype=np.float64)
    t = np.asarray(times, dtype=np.float64)
    if e.ndim != 2 or t.shape != e.shape[1:]:
        raise ValueError(f"errors must be (E, N) and times (N,), got shapes {e.shape} and {t.shape}")
    out = {}
    for prefix, w in (("full", e), ("steady", np.ascontiguousarray(e[:, t >= steady_start - 1e-9]))):
        if w.shape[1] == 0:
            for name in ("mean", "rmse", "max"):
                out[f"{prefix}_{name}"] = np.full(e.shape[0], np.nan)
            continue
        out[f"{prefix}_mean"] = w.mean(axis=1)
        out[f"{prefix}_rmse"] = np.sqrt(np.mean(w * w, axis=1))
        out[f"{prefix}_max"] = w.max(axis=1)
    return {key: out[key] for key in METRIC_KEYS}


# --- compiled: the metrics of many episodes straight from the (envs x steps) error history -----
_PW_BLOCK = 128  # numpy's pairwise-summation block (PW_BLOCKSIZE)


@njit(cache=True, inline="always")
def _term(x, i, square):
    v = x[i]
    return v * v if square else v


@njit(cache=True)
def _pairwise(x, lo, n, square):
    """Sum of x[lo:lo + n] (of its squares if ``square``) in numpy's pairwise order: below 8
    terms one by one; up to 128 terms eight interleaved partial sums, combined as
    ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7)), then the remainder; above that the two
    halves (the first a multiple of 8 long) summed separately. With the leading ``0.0 +`` of
    numpy's reduction, the result equals ``np.sum`` of that slice bit for bit."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += _term(x, i, square)
        return res
    if n <= _PW_BLOCK:
        r0, r1, r2, r3 = _term(x, lo, square), _term(x, lo + 1, square), \
            _term(x, lo + 2, square), _term(x, lo + 3, square)
        r4, r5, r6, r7 = _term(x, lo + 4, square), _term(x, lo + 5, square), \
            _term(x, lo + 6, square), _term(x, lo + 7, square)
        stop = n - n % 8
        for i in range(lo + 8, lo + stop, 8):
            r0 += _term(x, i, square)
            r1 += _term(x, i + 1, square)
            r2 += _term(x, i + 2, square)
            r3 += _term(x, i + 3, square)
            r4 += _term(x, i + 4, square)
            r5 += _term(x, i + 5, square)
            r6 += _term(x, i + 6, square)
            r7 += _term(x, i + 7, square)
        res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
        for i in range(lo + stop, lo + n):
            res += _term(x, i, square)
        return res
    n2 = n // 2
    n2 -= n2 % 8
    return _pairwise(x, lo, n2, square) + _pairwise(x, lo + n2, n - n2, square)


@njit(cache=True)
def _history_metrics(err_hist, ids, lengths, steady0, out):
    for q in range(ids.shape[0]):
        j = ids[q]
        n = lengths[q]
        row = err_hist[j]
        for w in range(2):
            lo = 0 if w == 0 else steady0
            m = n - lo
            if m <= 0:
                for c in range(3):
                    out[3 * w + c, j] = math.nan
                continue
            mx = row[lo]
            for i in range(lo + 1, n):
                v = row[i]
                if v > mx or v != v:  # (NaN propagates, as in np.max)
                    mx = v
            out[3 * w, j] = (0.0 + _pairwise(row, lo, m, False)) / m
            out[3 * w + 1, j] = math.sqrt((0.0 + _pairwise(row, lo, m, True)) / m)
            out[3 * w + 2, j] = mx


def history_metrics(err_hist: np.ndarray, ids: np.ndarray, lengths: np.ndarray, times: np.ndarray,
                    steady_start: float = 10.0) -> np.ndarray:
    """:func:`tracking_metrics` of episodes stored as rows of an (envs, steps) error history.

    Args:
        err_hist: (E, S) float64 error samples [m]; episode ``ids[q]`` is
            ``err_hist[ids[q], :lengths[q]]``.
        ids: env columns (int64), lengths: their sample counts (each 0..S).
        times: the sample times (S,) [s], increasing (the steady window is a suffix).
        steady_start: first time of the steady-state window [s].

    Returns:
        (6, E) array: row c holds ``METRIC_KEYS[c]`` of the listed envs, NaN elsewhere.
        Every value equals :func:`tracking_metrics`'s bit for bit (numpy's pairwise sums,
        replayed in compiled code: the per-episode numpy calls cost more than the sums).
    """
    e = np.asarray(err_hist)
    t = np.asarray(times, dtype=np.float64)
    ids = np.asarray(ids, dtype=np.int64)
    lengths = np.asarray(lengths, dtype=np.int64)
    if e.dtype != np.float64 or e.ndim != 2 or t.shape != e.shape[1:]:
        raise ValueError(f"err_hist must be an (E, S) float64 array and times (S,), got {e.dtype} {e.shape} "
                         f"and {t.shape}")
    if ids.shape != lengths.shape or ids.ndim != 1:
        raise ValueError(f"ids and lengths must be 1-D of equal length, got shapes {ids.shape} and {lengths.shape}")
    if ids.size and (ids.min() < 0 or ids.max() >= e.shape[0] or lengths.min() < 0 or lengths.max() > e.shape[1]):
        raise ValueError(f"ids must be in [0, {e.shape[0]}) and lengths in [0, {e.shape[1]}]")
    out = np.full((len(METRIC_KEYS), e.shape[0]), np.nan)
    _history_metrics(e, ids, lengths, steady_index(t, steady_start), out)
    return out


def steady_index(times: np.ndarray, steady_start: float) -> int:
    """The first sample of the steady-state window: the first of the increasing ``times`` [s] at
    or after ``steady_start`` (``len(times)`` if none)."""
    return int(np.searchsorted(np.asarray(times) >= steady_start - 1e-9, True)) if len(times) else 0


def history_metrics_into(err_hist: np.ndarray, ids: np.ndarray, lengths: np.ndarray, steady0: int,
                         out: np.ndarray) -> None:
    """:func:`history_metrics` without its checks, for callers whose arguments are right by
    construction (the vector env's step): writes column ``ids[q]`` of ``out`` (6, E) and nothing
    else; ``steady0`` from :func:`steady_index`; ``ids`` and ``lengths`` int64 arrays."""
    _history_metrics(err_hist, ids, lengths, steady0, out)
