"""Adaptive conformal inference: a level that moves with each miss, over a window of scores.

**ACI** (`aci`; Gibbs & Candès 2021, "Adaptive conformal inference under distribution
shift"): a level alpha_t, updated by alpha_{t+1} = alpha_t + gamma (alpha - err_t), and the
radius the (1 - alpha_t) empirical quantile of the last `window` scores (a ring buffer).
Guarantee (their Proposition 4.1), for ANY sequence of scores, adversarial or shifting, with
no assumption: |(1/T) sum_t err_t - alpha| <= (max(alpha_1, 1 - alpha_1) + gamma)/(gamma T)
(20,000 updates, gamma = 0.005: within 0.00905). It needs the extreme conventions of the
paper: alpha_t <= 0 gives r = +inf (not the largest finite score: that would let alpha_t fall
without bound and void the guarantee; a caller that must clip gives up the guarantee) and
alpha_t >= 1 the empty region, reported as r = 0 (covering an exact zero score only, which a
distance between a prediction and an observation almost surely is not). With feedback d
updates late (see `radius_in_force`) the same argument gives (max(alpha_1, 1 - alpha_1) +
(d + 1) gamma)/(gamma T). Pooled, a batch of scores per update: `batch="sequential"`
(default) takes one step per score, each judged against the radius issued with it, exactly
as a stream of those scores would: T counts scores, d the scores still awaited, and the
guarantee is on the fraction of scores outside their discs (what `gst_jax.coverage`
measures). `batch="mean"` takes one step per update with the batch's miss fraction: T counts
updates, and the guarantee is on the average over updates of those fractions (the fraction
of scores only when every batch has as many). The level's telescoping sum says more: over
any stretch of n scores, mean miss - alpha = (level at its start - level at its end) /
(gamma n), so the coverage error falls as the level settles.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gst_jax.conformal._src.base import BATCH_MODES, OnlineConformal, check_alpha, scores_and_mask


class ACIState(NamedTuple):
    """One ACI instance. level: () alpha_t, the level in force. radius: () the radius in force
    (from `level` and the window). scores: (W,) the last W scores in arrival order, a ring
    buffer (its first `count` entries hold scores); ordered: (W,) the same scores sorted,
    then +inf; count: () int32, how many scores the window holds (<= W); head: () int32,
    where the next score goes."""

    level: jax.Array
    radius: jax.Array
    scores: jax.Array
    ordered: jax.Array
    count: jax.Array  # type: ignore[assignment]  # shadows tuple.count (mypy: an override)
    head: jax.Array


def _aci_radius(level: jax.Array, ordered: jax.Array, count: jax.Array) -> jax.Array:
    """The (1 - level) empirical quantile inf{r : F_n(r) >= 1 - level} of the n = `count`
    scores, the ceil((1 - level) n)-th smallest; +inf for level <= 0 or no scores, 0 for
    level >= 1 (the empty region)."""
    rank = jnp.ceil((1 - level) * count)
    index = jnp.clip(rank.astype(jnp.int32) - 1, 0, ordered.shape[0] - 1)
    quantile = ordered[index]
    return jnp.where((level <= 0) | (count == 0), jnp.inf,
                     jnp.where(level >= 1, jnp.zeros_like(quantile), quantile))


def _remove_sorted(ordered: jax.Array, value: jax.Array) -> jax.Array:
    """`ordered` (sorted, +inf padded) without one entry equal to `value`, +inf appended."""
    index = jnp.sum(ordered < value)
    after = jnp.append(ordered[1:], jnp.inf)
    return jnp.where(jnp.arange(ordered.shape[0]) >= index, after, ordered)


def _insert_sorted(ordered: jax.Array, value: jax.Array) -> jax.Array:
    """`value` inserted into `ordered` (sorted, ending in +inf), its last entry dropped."""
    index = jnp.sum(ordered < value)
    before = jnp.concatenate([value[None], ordered[:-1]])
    position = jnp.arange(ordered.shape[0])
    return jnp.where(position < index, ordered, jnp.where(position == index, value, before))


def aci(alpha: float = 0.1, gamma: float = 0.005, window: int = 1000,
        batch: str = "sequential") -> OnlineConformal:
    """Adaptive conformal inference (Gibbs & Candès 2021) on a window of the last `window`
    scores; alpha: target miscoverage, gamma: step of the level; batch: "sequential" (one
    step per valid score) or "mean" (one step per update, with the batch's miss fraction).

    init(initial_radius=None, *, scores=None, dtype=None) -> ACIState: level alpha, no
      scores, radius `initial_radius` (+inf for None: nothing seen yet), the radius in force
      until the first update; or, given calibration scores (n,), a window holding them (the
      last `window`) and their (1 - alpha) quantile as the radius (+inf for none;
      `initial_radius` unused).
    update(state, scores (B,), mask (B,) = None, *, radius_in_force = None, uniform = None)
      -> (state, radius): each valid score misses when it is above the radius in force
      (`state.radius`, or `radius_in_force`, () or (B,), the radii issued with the
      predictions these scores belong to, for delayed feedback: `DelayedScores.issued`);
      level += gamma (alpha - miss) for each of them (sequential) or gamma (alpha - mean miss)
      once (mean); the valid scores enter the window in order, each pushing out the oldest
      once it is full; radius = the (1 - level) quantile of the window. Scores must be finite
      where valid. No valid score: the level and the window stay (the radius is their
      quantile, the same unless `init`'s initial_radius was still in force). `uniform` is
      accepted for the common signature and unused: ACI draws nothing.

    The window is kept sorted as well, one score in and one out in O(W) each, so that an
    update costs O(B W), not a sort of W (measured: benchmarks/bench_conformal.py).
    """
    check_alpha(alpha)
    if window < 1 or batch not in BATCH_MODES:
        raise ValueError(f"window must be >= 1 (got {window}) and batch one of {BATCH_MODES} "
                         f"(got {batch!r})")

    def init(initial_radius=None, *, scores: jax.Array | None = None, dtype=None
             ) -> ACIState:
        level = jnp.asarray(alpha, dtype or float)
        radius = jnp.inf if initial_radius is None else initial_radius
        state = ACIState(level=level, radius=jnp.asarray(radius, level.dtype),
                         scores=jnp.zeros((window,), level.dtype),
                         ordered=jnp.full((window,), jnp.inf, level.dtype),
                         count=jnp.zeros((), jnp.int32), head=jnp.zeros((), jnp.int32))
        if scores is None:
            return state
        scores = jnp.asarray(scores, level.dtype)
        carry, _ = jax.lax.scan(push, (state.scores, state.ordered, state.count, state.head),
                                (scores, jnp.ones(scores.shape, bool)))
        return state._replace(radius=_aci_radius(level, carry[1], carry[2]),
                              scores=carry[0], ordered=carry[1], count=carry[2], head=carry[3])

    def push(carry, score_and_valid):
        scores, ordered, count, head = carry
        score, valid = score_and_valid
        full = count == window
        ordered_out = jnp.where(full, _remove_sorted(ordered, scores[head]), ordered)
        ordered = jnp.where(valid, _insert_sorted(ordered_out, score), ordered)
        scores = jnp.where(valid, scores.at[head].set(score), scores)
        count = jnp.where(valid & ~full, count + 1, count)
        head = jnp.where(valid, (head + 1) % window, head)
        return (scores, ordered, count, head), None

    def update(state: ACIState, scores: jax.Array, mask: jax.Array | None = None, *,
               radius_in_force: jax.Array | None = None, uniform: jax.Array | None = None
               ) -> tuple[ACIState, jax.Array]:
        scores, mask = scores_and_mask(scores, mask, state.scores.dtype)
        radius = state.radius if radius_in_force is None else radius_in_force
        present = jnp.sum(mask)
        misses = jnp.sum(mask & (scores > radius))
        # sequential: the sum of the per-score steps, each score judged against the radius
        # issued with it (the batch's radii were all issued before any of it came back).
        steps = present if batch == "sequential" else jnp.minimum(present, 1)
        err = misses / jnp.maximum(present, 1)
        level = state.level + gamma * steps * (alpha - err)
        level = level.astype(state.level.dtype)
        carry = (state.scores, state.ordered, state.count, state.head)
        if scores.shape[0] == 1:
            carry, _ = push(carry, (scores[0], mask[0]))
        else:
            carry, _ = jax.lax.scan(push, carry, (scores, mask))
        buffer, ordered, count, head = carry
        radius = _aci_radius(level, ordered, count)
        return ACIState(level=level, radius=radius, scores=buffer, ordered=ordered,
                        count=count, head=head), radius

    return OnlineConformal(init, update)
