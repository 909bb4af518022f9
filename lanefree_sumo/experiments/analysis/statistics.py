"""Percentile-bootstrap confidence intervals over runs (seeds): of a mean (the sweep summary) and of a
difference of two groups' means (the claims check). Fixed seeds, so a summary recomputed from the same
episodes gives the same numbers."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

CI_LEVEL = 0.95
BOOTSTRAP_RESAMPLES = 10_000


def _interval(samples: np.ndarray, level: float) -> tuple[float, float]:
    low, high = np.quantile(samples, [(1 - level) / 2, 1 - (1 - level) / 2])
    return float(low), float(high)


def _resampled_means(values: np.ndarray, rng: np.random.Generator, resamples: int) -> np.ndarray:
    """Means of ``resamples`` resamples of ``values`` with replacement."""
    return values[rng.integers(0, values.size, size=(resamples, values.size))].mean(axis=1)


def bootstrap_ci(values: Sequence[float], level: float = CI_LEVEL, resamples: int = BOOTSTRAP_RESAMPLES,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile-bootstrap confidence interval of the mean of ``values`` (resampling the values
    with replacement); (nan, nan) for fewer than 2 values."""
    x = np.asarray(values, dtype=float)
    if x.size < 2:
        return math.nan, math.nan
    return _interval(_resampled_means(x, np.random.default_rng(seed), resamples), level)


def bootstrap_difference_ci(a: Sequence[float], b: Sequence[float], level: float = CI_LEVEL,
                            resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """Percentile-bootstrap confidence interval of mean(a) − mean(b), each group resampled on its own
    (a's resamples drawn first); (nan, nan) when a group is empty."""
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if not x.size or not y.size:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    return _interval(_resampled_means(x, rng, resamples) - _resampled_means(y, rng, resamples), level)
