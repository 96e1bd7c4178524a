"""Whole-path regions calibrated across trajectories: one disc per horizon step, all P held.

A prediction of P steps is judged as a whole: with s_k = ||predicted[k] - observed[k]|| its
horizon-k score, it is covered by radii r (P,) when s_k <= r_k at every step k observed.
Per-step discs, each of split-conformal level 1 - alpha, do not hold a path: the union of
their misses is larger than any one of them (tests/test_whole_path.py: 0.67 of random-walk
paths inside all twelve discs of level 0.9). A union bound (each at alpha / P) holds the path
but is too large when the steps' errors move together, as a walk's do (there: 0.96 of paths,
radii summing to 11.2 m against these regions' 9.2 m, which hold 0.90).

**Normalised-max regions** (`whole_path_region`), the construction of Cleaveland, Lee, Pappas
& Lindemann (2024, "Conformal prediction regions for time series using linear
complementarity programming"): the calibration paths are split in two, D1 (`fit`) and D2
(the rest). D1 fixes positive per-step scales sigma_k (the weights alpha_k = 1/sigma_k of the
paper's score max_k alpha_k R_k). Each path of D2 gets one score, the largest of its observed
steps' scores over their scales,

    m = max_{k observed} s_k / sigma_k,

q is the split-conformal quantile of the scores m of D2's n paths that have an observed
step (the ceil((n+1)(1-alpha))-th
smallest; +inf when that rank exceeds n), and the radii are r_k = q sigma_k. A new path is
covered exactly when its m <= q (up to the rounding of q sigma_k). Guarantee (split
conformal on the scores m): if D2's paths and the new one are exchangeable (their scores
and masks) and the scales depend on D1 alone, then

    1 - alpha <= P(every observed step of the new path lies in its disc) < 1 - alpha + 1/(n+1),

the upper bound when the m have no ties (continuous scores); the probability is over D2
and the new path, D1 fixed. With continuous scores it is exactly ceil((n+1)(1-alpha))/(n+1)
on average over D2, and, given D2, the coverage is Beta(l, n + 1 - l) distributed, l that
rank. The scales only decide the regions' shape: any rule that does not look at D2 keeps
the guarantee. Cleaveland et al. choose the weights on D1 by an optimisation (a linear
complementarity program) that makes the regions small; here, by default, sigma_k is the
empirical `scale_level` quantile (1 - alpha for None) of D1's observed horizon-k scores (the
ceil(level n_k)-th smallest of its n_k), so that every step's normalised score has its D1
quantile at 1 and no one step decides the max (a closed form, jit-able; not their program,
so the shape may be less tight than theirs, the guarantee the same); a step D1 never
observed gets sigma_k = +inf (r_k = +inf: it was never calibrated), and a zero quantile is
raised to the smallest positive float. Or pass scales fixed elsewhere (other data, a model's
own variance): then every path not marked `fit` calibrates q.

Paths with no observed step are left out (they cannot miss). Missing steps are allowed
elsewhere: a path is scored and judged on the steps it has, which keeps the guarantee as
long as which steps are missing is exchangeable across paths too.

Not here: CAFHT (Zhou, Lindemann & Sesia 2024) runs ACI along each trajectory as its steps
are revealed one at a time, the regions of step k+1 made after step k is seen; the regions
here are issued at once for all P steps of a prediction, which is what a planner gets.

`paths_inside` judges paths against radii (these or any others, e.g. per-step discs), and
`joint_coverage` reports how many of the test paths were inside, with the exact binomial
(Clopper-Pearson) interval of that fraction (`binomial.py`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.conformal._src.base import check_alpha
from gst_jax.conformal._src.binomial import clopper_pearson
from gst_jax.conformal._src.split import split_radius


class PathRegion(NamedTuple):
    """Whole-path regions. scales: (P,) sigma_k, from D1 or given; quantile: () q, the
    split-conformal quantile of D2's normalised scores; radii: (P,) q sigma_k, metres (+inf
    where q or sigma_k is); count: () int32, n, the paths of D2 that calibrated q (the upper
    bound on coverage is 1 - alpha + 1/(n+1))."""

    scales: jax.Array
    quantile: jax.Array
    radii: jax.Array
    count: jax.Array  # type: ignore[assignment]  # shadows tuple.count (mypy: an override)


class JointCoverage(NamedTuple):
    """Of `paths` test paths, `covered` had every observed step inside; `fraction` their share
    (NaN for none) and [lower, upper] its exact Clopper-Pearson interval at `confidence`."""

    covered: int
    paths: int
    fraction: float
    lower: float
    upper: float
    confidence: float


def _scores_and_mask(scores, mask) -> tuple[jax.Array, jax.Array]:
    scores = jnp.asarray(scores)
    scores = scores.astype(jnp.result_type(scores.dtype, float))
    if scores.ndim != 2:
        raise ValueError(f"scores must be (paths, P), one row per path, got shape "
                         f"{scores.shape}; vmap over further axes")
    mask = jnp.ones(scores.shape, bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != scores.shape:
        raise ValueError(f"mask {mask.shape} must have the shape of scores {scores.shape}")
    return scores, mask


def step_quantiles(scores: jax.Array, mask: jax.Array | None, level: float) -> jax.Array:
    """Per horizon step k, the empirical `level` quantile of the observed scores (paths, P):
    the ceil(level n_k)-th smallest of the n_k observed (at least the smallest); +inf for a
    step never observed. The default scales of `whole_path_region`, from D1's paths."""
    scores, mask = _scores_and_mask(scores, mask)
    if scores.shape[0] == 0:
        return jnp.full(scores.shape[1:], jnp.inf, scores.dtype)
    count = jnp.sum(mask, axis=0)                                                   # (P,)
    ordered = jnp.sort(jnp.where(mask, scores, jnp.inf), axis=0)
    rank = jnp.maximum(jnp.ceil(level * count), 1).astype(jnp.int32)
    index = jnp.clip(rank - 1, 0, scores.shape[0] - 1)
    return jnp.take_along_axis(ordered, index[None], axis=0)[0]


def path_scores(scores: jax.Array, mask: jax.Array | None, scales: jax.Array) -> jax.Array:
    """Each path's normalised score m = max over its observed steps of s_k / sigma_k (paths,);
    -inf for a path with no observed step. scores, mask (paths, P); scales (P,) positive."""
    scores, mask = _scores_and_mask(scores, mask)
    ratios = scores / jnp.asarray(scales, scores.dtype)
    return jnp.max(jnp.where(mask, ratios, -jnp.inf), axis=-1, initial=-jnp.inf)


def whole_path_region(scores: jax.Array, mask: jax.Array | None, alpha: float, *,
                      fit: jax.Array | None = None, scales: jax.Array | None = None,
                      scale_level: float | None = None) -> PathRegion:
    """Normalised-max whole-path regions (this module's docstring) from calibration paths'
    scores (paths, P) (`mask` (paths, P): the observed steps; None: all).

    fit: (paths,) bool, the paths of D1, which fix the scales (the `scale_level` quantile of
      each step, 1 - alpha for None); the others calibrate q. Needed unless `scales` is given.
    scales: (P,) positive sigma_k fixed without these paths' D2; then the paths not in `fit`
      (all, for None) calibrate q.
    alpha in (0, 1): the target miscoverage of whole paths. Scores must be finite where
      observed.

    Pure: jits (alpha and scale_level static) and vmaps over repetitions or scenes."""
    check_alpha(alpha)
    if scale_level is not None and not 0 < scale_level <= 1:
        raise ValueError(f"scale_level must lie in (0, 1], got {scale_level}")
    scores, mask = _scores_and_mask(scores, mask)
    if scales is None and fit is None:
        raise ValueError("whole_path_region needs scales, or paths marked `fit` to fix "
                         "them: the paths that calibrate q must not choose the scales")
    fit = jnp.zeros(scores.shape[:1], bool) if fit is None else jnp.asarray(fit, bool)
    if fit.shape != scores.shape[:1]:
        raise ValueError(f"fit {fit.shape} must hold one flag per path {scores.shape[:1]}")
    if scales is None:
        level = 1 - alpha if scale_level is None else scale_level
        scales = step_quantiles(scores, mask & fit[:, None], level)
        scales = jnp.maximum(scales, jnp.finfo(scores.dtype).tiny)
    scales = jnp.asarray(scales, scores.dtype)
    m = path_scores(scores, mask, scales)
    calibrating = ~fit & jnp.any(mask, axis=-1)
    quantile = split_radius(m, calibrating, alpha)
    radii = jnp.where(jnp.isinf(scales) | jnp.isinf(quantile), jnp.inf, quantile * scales)
    return PathRegion(scales=scales, quantile=quantile, radii=radii,
                      count=jnp.sum(calibrating).astype(jnp.int32))


def paths_inside(scores: jax.Array, mask: jax.Array | None, radii: jax.Array) -> jax.Array:
    """Whether each path (paths, P) has every observed step within its radius (P,): (paths,)
    bool (True for a path with no observed step; leave those out of a count)."""
    scores, mask = _scores_and_mask(scores, mask)
    return jnp.all(~mask | (scores <= jnp.asarray(radii, scores.dtype)), axis=-1)


def joint_coverage(inside, present=None, confidence: float = 0.95) -> JointCoverage:
    """How many of the present paths (`present` (paths,) bool; None: all) were inside
    (`inside` (paths,) bool, from `paths_inside`), their fraction and its exact
    Clopper-Pearson interval at `confidence` (the paths taken as independent trials, as
    exchangeable test paths given the calibration are). Host side: returns Python numbers."""
    inside = np.asarray(inside, bool).reshape(-1)
    present = np.ones(inside.shape, bool) if present is None else \
        np.asarray(present, bool).reshape(-1)
    if present.shape != inside.shape:
        raise ValueError(f"present {present.shape} must match inside {inside.shape}")
    paths, covered = int(present.sum()), int((inside & present).sum())
    lower, upper = clopper_pearson(covered, paths, confidence)
    return JointCoverage(covered=covered, paths=paths,
                         fraction=covered / paths if paths else float("nan"),
                         lower=lower, upper=upper, confidence=float(confidence))
