"""Paired comparisons: two settings measured on the same units (episodes, pedestrians).

Where two predictors or two region settings play the same episodes, their difference is
measured episode by episode, which is far sharper than comparing two independent rates: the
episodes both succeed or both fail in carry no information about the difference, only the
discordant ones do.

    paired_rates(success_a, success_b)   # difference, 95 % interval, McNemar's exact p
    paired_means(time_a, time_b)         # difference of means, paired bootstrap interval

numpy only.
"""

from __future__ import annotations

import math

import numpy as np

# Resamples of the paired bootstrap, and its seed: the same records give the same interval.
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact p-value of McNemar's test: under "no difference", each of the
    only_a + only_b discordant units is a's with probability 1/2."""
    discordant = only_a + only_b
    if discordant == 0:
        return 1.0
    tail = sum(math.comb(discordant, k) for k in range(min(only_a, only_b) + 1))
    return min(1.0, 2.0 * tail / 2.0 ** discordant)


def paired_rates(a: np.ndarray, b: np.ndarray, level: float = 0.95) -> dict:
    """Rate of a minus rate of b over the same units (0/1 or booleans, (U,) each): the
    difference, its paired-bootstrap interval at `level`, the discordant counts (only_a: a
    yes and b no) and McNemar's exact p-value."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    _check_paired(a, b)
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(~a & b))
    low, high = _bootstrap_interval(a.astype(float) - b.astype(float), level)
    return {"difference": (only_a - only_b) / len(a), "low": low, "high": high,
            "only_a": only_a, "only_b": only_b, "p": mcnemar_exact(only_a, only_b),
            "units": len(a)}


def paired_means(a: np.ndarray, b: np.ndarray, level: float = 0.95) -> dict:
    """Mean of a minus mean of b over the same units ((U,) each; units where either is NaN
    left out): the difference and its paired-bootstrap interval at `level`."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    _check_paired(a, b)
    both = ~(np.isnan(a) | np.isnan(b))
    difference = a[both] - b[both]
    low, high = _bootstrap_interval(difference, level)
    return {"difference": float(difference.mean()) if len(difference) else math.nan,
            "low": low, "high": high, "units": int(both.sum())}


def excludes_zero(comparison: dict) -> bool:
    """Whether a comparison's interval lies wholly on one side of zero."""
    return comparison["low"] > 0 or comparison["high"] < 0


def _check_paired(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"paired measures need two 1-d arrays over the same units, got shapes "
                         f"{a.shape} and {b.shape}")


def _bootstrap_interval(difference: np.ndarray, level: float) -> tuple[float, float]:
    """Percentile interval of the mean of `difference` (U,) over units resampled with
    replacement (the units, not the two settings, are what varies)."""
    if len(difference) == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    draws = rng.integers(0, len(difference), (BOOTSTRAP_RESAMPLES, len(difference)))
    means = difference[draws].mean(axis=1)
    tail = (1 - level) / 2
    low, high = np.quantile(means, [tail, 1 - tail])
    return float(low), float(high)
