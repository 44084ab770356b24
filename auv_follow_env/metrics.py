"""The paper's tracking metrics, eqs. (64)-(65), as pure array functions.

e_k = ||e_p(t_k)||; mean = (1/N) sum e_k; RMSE = sqrt((1/N) sum e_k^2); max = max e_k,
over the full run and over the steady-state window t >= steady_start (10 s in the paper).
"""

from __future__ import annotations

import numpy as np

__all__ = ["METRIC_KEYS", "tracking_metrics", "window_metrics", "batch_tracking_metrics"]

#: keys of :func:`tracking_metrics`, in table order
METRIC_KEYS: tuple[str, ...] = (
    "full_mean", "full_rmse", "full_max", "steady_mean", "steady_rmse", "steady_max")


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
