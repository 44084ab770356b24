"""Statistics as pure array functions: IQM, stratified-bootstrap confidence intervals and the
probability of improvement (rliable's definitions, lower-is-better scores)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from scipy import stats

import auv_follow_env  # noqa: F401  (registers the ids)

DEFAULT_RESAMPLES = 10_000


#: most bootstrap resamples accepted (a million take minutes per row; more only waits longer)
MAX_RESAMPLES = 1_000_000


DEFAULT_BOOTSTRAP_SEED = 0


def iqm(x: np.ndarray, axis: int | None = -1) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50 % (``scipy.stats.trim_mean(x, 0.25)``,
    rliable's ``aggregate_iqm``); with n samples, ``int(0.25 n)`` are cut from each end."""
    return stats.trim_mean(np.asarray(x, dtype=np.float64), 0.25, axis=axis)


def _mean(x: np.ndarray, axis: int | None = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


_STATISTICS: dict[str, Callable[..., np.ndarray]] = {"iqm": iqm, "mean": _mean}


def stratified_bootstrap_ci(strata: Sequence[Sequence[float]], statistic: str | Callable = "iqm", *,
                            confidence: float = 0.95, n_resamples: int = DEFAULT_RESAMPLES,
                            seed: int = DEFAULT_BOOTSTRAP_SEED, paired: bool | None = None
                            ) -> tuple[float, float, float]:
    """Point estimate and percentile-bootstrap CI of ``statistic`` over the pooled strata.

    Each stratum is resampled with replacement (its size kept), the resampled strata are
    pooled and the statistic is taken over the pool (rliable's stratified bootstrap, with
    ``scipy.stats.bootstrap`` doing the resampling). With ``paired`` the strata are aligned
    (entry j of every stratum is the same test seed) and one draw of indices is applied to all
    of them: the test seed, not the episode, is the unit resampled - several training runs
    scored on the same seeds do not count as independent conditions. ``None``: paired when
    there are several strata of equal length.

    Args:
        strata: one 1-D sequence of scores per stratum (e.g. per training run).
        statistic: ``"iqm"``, ``"mean"`` or a function ``f(x, axis=-1)``.
        confidence: CI level in (0, 1).
        n_resamples: bootstrap resamples (>= 1).
        seed: seed of the resampling generator (same seed, same CI).

    Returns:
        (estimate, low, high). A pool of one sample gives a zero-width CI.

    Raises:
        ValueError: empty strata, non-finite scores, unknown statistic, bad confidence.
    """
    if isinstance(statistic, str):
        if statistic not in _STATISTICS:
            raise ValueError(f"statistic={statistic!r} is unknown: valid statistics are {list(_STATISTICS)} "
                             f"or a function f(x, axis)")
        statistic = _STATISTICS[statistic]
    if not (isinstance(confidence, (int, float)) and 0.0 < confidence < 1.0):
        raise ValueError(f"confidence={confidence!r} is invalid: must be a number in (0, 1)")
    if isinstance(n_resamples, bool) or not isinstance(n_resamples, (int, np.integer)) or n_resamples < 1:
        raise ValueError(f"n_resamples={n_resamples!r} is invalid: must be an integer >= 1")
    arrays = [np.asarray(s, dtype=np.float64).reshape(-1) for s in strata]
    if not arrays or any(a.size == 0 for a in arrays):
        raise ValueError(f"strata={strata!r} is invalid: give at least one non-empty stratum")
    pooled = np.concatenate(arrays)
    if not np.all(np.isfinite(pooled)):
        raise ValueError("strata contain NaN or inf scores: replace them (e.g. by the failure value) first")
    est = float(statistic(pooled, axis=-1))
    if pooled.size == 1 or np.all(pooled == pooled[0]):
        return est, est, est
    resampled = tuple(a for a in arrays)
    if paired is None:
        paired = len(arrays) > 1 and len({a.size for a in arrays}) == 1
    if paired and len({a.size for a in arrays}) != 1:
        raise ValueError(f"paired=True needs strata of equal length, got sizes {[a.size for a in arrays]}")

    def pooled_stat(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
        return statistic(np.concatenate(samples, axis=axis), axis=axis)

    res = stats.bootstrap(resampled, pooled_stat, n_resamples=int(n_resamples), confidence_level=confidence,
                          method="percentile", vectorized=True, paired=bool(paired), axis=-1, batch=1000,
                          rng=np.random.default_rng(seed))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return est, lo, hi


def _poi(x: np.ndarray, y: np.ndarray, axis: int = -1) -> np.ndarray:
    """P(X < Y) + P(X = Y)/2 over all pairs (lower is better), batched over leading axes."""
    x = np.moveaxis(np.asarray(x, dtype=np.float64), axis, -1)
    y = np.moveaxis(np.asarray(y, dtype=np.float64), axis, -1)
    xb, yb = x[..., :, None], y[..., None, :]
    return ((xb < yb).mean(axis=(-2, -1)) + 0.5 * (xb == yb).mean(axis=(-2, -1)))


def probability_of_improvement(x: Sequence[float], y: Sequence[float], *, confidence: float = 0.95,
                               n_resamples: int = 2000, seed: int = DEFAULT_BOOTSTRAP_SEED
                               ) -> tuple[float, float, float]:
    """Probability that an episode of X has a *lower* error than an episode of Y (rliable's
    probability of improvement, Mann-Whitney U / (n_x n_y), for lower-is-better scores),
    with a percentile-bootstrap CI (X and Y resampled independently).

    Returns:
        (estimate, low, high).
    """
    xa, ya = np.asarray(x, dtype=np.float64).reshape(-1), np.asarray(y, dtype=np.float64).reshape(-1)
    if xa.size == 0 or ya.size == 0:
        raise ValueError(f"x and y must be non-empty, got sizes {xa.size} and {ya.size}")
    est = float(_poi(xa, ya))
    if xa.size == 1 and ya.size == 1:
        return est, est, est
    res = stats.bootstrap((xa, ya), _poi, n_resamples=int(n_resamples), confidence_level=confidence,
                          method="percentile", vectorized=True, paired=False, axis=-1,
                          batch=max(1, 4_000_000 // max(xa.size * ya.size, 1)), rng=np.random.default_rng(seed))
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    if not (np.isfinite(lo) and np.isfinite(hi)):  # degenerate bootstrap distribution
        lo = hi = est
    return est, lo, hi
