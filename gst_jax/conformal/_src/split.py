"""Split conformal: a radius fixed from calibration scores.

**Split conformal** (`split_radius`): the ceil((n+1)(1-alpha))-th smallest of n calibration
scores (+inf when that rank exceeds n), fixed afterwards. Guarantee: if the calibration scores
and the new score are exchangeable, P(s <= r) >= 1 - alpha (and < 1 - alpha + 1/(n+1)
without ties). Nothing holds once the scores' distribution shifts (tests/test_conformal.py:
after the score scale doubles, coverage falls from 0.9 to about 0.44).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from gst_jax.conformal._src.base import check_alpha, scores_and_mask


def split_radius(scores: ArrayLike, mask: ArrayLike | None, alpha: float) -> jax.Array:
    """The split-conformal radius of calibration scores (n,) (`mask` (n,): the valid ones):
    the ceil((n+1)(1-alpha))-th smallest valid score, i.e. the ceil((n+1)(1-alpha))/n
    empirical quantile; +inf when that rank exceeds n (too few scores for the level) or
    n = 0. alpha in (0, 1). For one horizon step; vmap over horizon steps (scores (P, n))."""
    check_alpha(alpha)
    scores = jnp.asarray(scores)
    scores, mask = scores_and_mask(scores, mask, jnp.result_type(scores.dtype, float))
    if scores.shape[0] == 0:
        return jnp.asarray(jnp.inf, scores.dtype)
    n = jnp.sum(mask)
    rank = jnp.ceil((n + 1) * (1 - alpha))
    ordered = jnp.sort(jnp.where(mask, scores, jnp.inf))
    index = jnp.clip(rank.astype(jnp.int32) - 1, 0, scores.shape[0] - 1)
    return jnp.where(rank > n, jnp.inf, ordered[index])


def start_radius(alpha: float, initial_radius, scores: jax.Array | None, dtype) -> jax.Array:
    """Where a method that tracks a radius (DtACI, PID) starts: `initial_radius` (0 for
    None), or, given calibration scores (n,), their split-conformal radius, and
    `initial_radius` where they are too few for the level; in `dtype` (float for None)."""
    start = jnp.asarray(0.0 if initial_radius is None else initial_radius, dtype or float)
    if scores is None:
        return start
    radius = split_radius(jnp.asarray(scores, start.dtype), None, alpha)
    return jnp.where(jnp.isfinite(radius), radius, start).astype(start.dtype)
