"""Calibrated uncertainty discs around predicted positions, online: split conformal, ACI, DtACI.

A predictor gives, at every time step t and for every tracked person, positions for horizon
steps k = 1..P. The nonconformity score of the horizon-k prediction made at t is the distance
`s = ||predicted_t[k] - observed_{t+k}||`, known k steps later. A region is a disc of radius r
around the predicted position; it covers when `s <= r`. Each method below turns the scores
seen so far into the radius to use next, aiming at miscoverage `alpha` (e.g. 0.1): one
instance per horizon step (pooled) or per track and horizon step (per track), always as
separate instances, since scores of different horizons have different scales.

Each online method is a pair of pure functions, like optax's `GradientTransformation`:
`init(...) -> state` and `update(state, scores, mask, ...) -> (state, radius)`, the state a
NamedTuple of arrays that holds `radius`, the radius in force until the next update. They jit,
vmap over any leading axes (tracks, horizon steps, environments) and scan over time:

    method = conformal.dtaci(alpha=0.1)
    state = jax.vmap(jax.vmap(method.init))(q0)                  # q0 (N, P): 0.1 * k metres
    feed = conformal.score_buffer_init(num_tracks=N, horizon=P)
    # per time step:
    feed, delayed = conformal.score_buffer_update(feed, predicted, valid, observed, detected)
    per_track = jax.vmap(jax.vmap(method.update))                  # batch of 1 score each
    state, radius = per_track(state, delayed.scores[..., None], delayed.mask[..., None],
                              jax.random.uniform(key, (N, P)))     # radius (N, P)
    feed = conformal.record_issued(feed, radius)                  # back with its scores

    pooled = jax.vmap(method.update)                               # one instance per horizon
    state, radius = pooled(state, delayed.scores.T, delayed.mask.T, uniforms_p)  # (P,)

**Pooled vs per track.** Per track: an instance per (track, horizon step) learns that
person's radius from that person's scores alone (GenSafeNav's ROS 2 node; a new person starts
from scratch). Pooled: an instance per horizon step gets, at each time step, the batch of
scores of every detected track (at most one per track; `mask` marks those present), and gives
one radius to everyone. A masked entry changes nothing; an update whose entries are all
masked leaves the state as it was.

**Split conformal** (`split_radius`): the ceil((n+1)(1-alpha))-th smallest of n calibration
scores (+inf when that rank exceeds n), fixed afterwards. Guarantee: if the calibration scores
and the new score are exchangeable, P(s <= r) >= 1 - alpha (and < 1 - alpha + 1/(n+1)
without ties). Nothing holds once the scores' distribution shifts (tests/test_conformal.py:
after the score scale doubles, coverage falls from 0.9 to about 0.44).

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

**DtACI** (`dtaci`): GenSafeNav's (tasl-lab/GenSafeNav, CoRL 2025) port of Gibbs & Candès
2022 ("Conformal inference for online prediction with arbitrary distribution shifts",
Algorithm 1; R `conformalAdaptStable`), whose K experts hold a radius q_i (metres) instead of
a level: each expert is ACI-like quantile tracking with its own step gamma_i, q_i <- q_i +
gamma_i (1{q_i < s} - alpha), and exponential weights with a fixed share sigma choose among
them by their pinball losses; the radius is the drawn expert's q_i (GenSafeNav) or the
probability-weighted mean (`output="mean"`, deterministic), clipped to [0, r_max].

With scores in [0, B], put a_i = 1 - q_i/B and beta_t = 1 - s_t/B in [0, 1]: the update with
the consistent loss (below) is then exactly the paper's Algorithm 1 on beta_t, with steps
gamma_i/B and learning rate eta B (a miss 1{q_i < s} is 1{a_i > beta_t}, and the pinball
loss of beta_t - a_i at level alpha is the consistent loss of s - q_i over B). So the
paper's guarantees hold as stated, for any sequence of bounded scores (no other
assumption): the long-run miscoverage of the drawn expert is within a term of order
1/(gamma_min T) plus one that shrinks with eta and sigma of alpha (close to, not exactly,
alpha for fixed eta, sigma), and the strongly adaptive regret: on every interval of length
I, the expected pinball loss exceeds that of the best fixed threshold on the interval by
O(sqrt(I log(K I))) when eta and sigma are tuned to I (and a dynamic version in the path
length of the best thresholds); the constants are the paper's. Each expert on its own also
has |(1/T) sum_t 1{s_t > q_i,t} - alpha| <= (B + gamma_i)/(gamma_i T) for q0 in [0, B]
(quantile tracking; Angelopoulos, Candès & Tibshirani 2023, Proposition 1), whatever the
loss.

The loss: the (1 - alpha) quantile of the scores, which the experts track, has the pinball
loss `(1 - alpha) max(u, 0) + alpha max(-u, 0)` with u = s - q (`loss="consistent"`, the
default; the R code's loss under the map above). GenSafeNav kept the R code's formula
`alpha u - min(u, 0)` but with u = s - q, whose sign is the opposite of the R code's
beta_t - alpha_t (`loss="gensafenav"`): the pinball loss of the alpha quantile. It charges a
too-large radius (1 - alpha) per metre and a too-small one alpha per metre, so the weights
favour the experts with small radii, against the experts' own target: lower coverage
(tests/test_conformal.py: 0.895 and 0.892 against 0.899 for the consistent loss, on an
i.i.d. and a shifting stream), and the regret statement is about the alpha quantile. Its
`np.vectorize(lambda x: min(x, 0))` also infers an integer output type when the first
expert's u is positive, truncating the other experts' min(u, 0) to integers; that bug is not
reproduced here.

Batched (pooled) DtACI feedback, `batch=`: "sequential" (default) applies the update once per
valid score, in the batch's order, exactly as a stream of those scores would: the exact
generalisation, with each expert's guarantee per score. "mean" makes one step with the mean
pinball loss and the mean miss indicator of the batch (all scored against the same q_i), the
online-gradient step on the batch's average loss, with the guarantees per update like ACI's
pooled mode. The expert is drawn once per update after the batch: the experts and weights do
not depend on which expert was drawn, so drawing after every score and keeping the last is
the same in distribution. With one score per update (per track), both modes equal GenSafeNav.

Randomness is explicit: `update` takes a uniform in [0, 1) per update and picks the expert
as numpy's `np.random.choice(K, p=p)` does (`searchsorted(cumsum(p) / sum, u, "right")`), so
that replaying numpy's uniforms replays GenSafeNav (benchmarks/bench_conformal.py).

`score_buffer_init` / `score_buffer_update` turn a stream of predictions and observations
into the delayed scores: at each step, for k = 1..P, the horizon-k score of the prediction
made k steps earlier, masked where that track's prediction was not valid then or the track is
not detected now; `record_issued` keeps the radii given out with a prediction, which come
back with its scores (ACI's `radius_in_force`, for the coverage of the discs actually used). Track slots are fixed: a slot given to a new person must be cleared with
`reset_slots` (and its per-track conformal state re-initialised by the caller).

The plain-numpy references of the update equations are in gst_jax/testing/
conformal_reference.py; tests/test_conformal.py checks these functions against them.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["ACIState", "DelayedScores", "DtACIState", "OnlineConformal", "ScoreBufferState",
           "aci", "dtaci", "record_issued", "reset_slots", "score_buffer_init",
           "score_buffer_update", "split_radius"]

LOSSES = ("consistent", "gensafenav")
OUTPUTS = ("sample", "mean")
BATCH_MODES = ("sequential", "mean")


@dataclasses.dataclass(frozen=True)
class OnlineConformal:
    """An online conformal method: `init(...) -> state`, `update(state, scores, mask, ...) ->
    (state, radius)`; both pure, for one instance (vmap for more)."""

    init: Callable[..., Any]
    update: Callable[..., tuple[Any, jax.Array]]


def _scores_and_mask(scores, mask, dtype) -> tuple[jax.Array, jax.Array]:
    scores = jnp.asarray(scores, dtype)
    if scores.ndim != 1:
        raise ValueError(f"scores must be a batch (B,) for one instance, got shape "
                         f"{scores.shape}; vmap over tracks or horizon steps")
    mask = jnp.ones(scores.shape, bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != scores.shape:
        raise ValueError(f"mask {mask.shape} must have the shape of scores {scores.shape}")
    return scores, mask


def _check_alpha(alpha) -> None:
    """Refuse a target miscoverage outside (0, 1) (NaN included); a traced one is the
    caller's to check."""
    try:
        value = float(alpha)
    except TypeError:                     # a tracer or an array of several
        return
    if not 0 < value < 1:
        raise ValueError(f"alpha must lie strictly between 0 and 1, got {alpha}")


# Split conformal -----------------------------------------------------------------------------


def split_radius(scores: jax.Array, mask: jax.Array | None, alpha: float) -> jax.Array:
    """The split-conformal radius of calibration scores (n,) (`mask` (n,): the valid ones):
    the ceil((n+1)(1-alpha))-th smallest valid score, i.e. the ceil((n+1)(1-alpha))/n
    empirical quantile; +inf when that rank exceeds n (too few scores for the level) or
    n = 0. alpha in (0, 1). For one horizon step; vmap over horizon steps (scores (P, n))."""
    _check_alpha(alpha)
    scores = jnp.asarray(scores)
    scores, mask = _scores_and_mask(scores, mask, jnp.result_type(scores.dtype, float))
    if scores.shape[0] == 0:
        return jnp.asarray(jnp.inf, scores.dtype)
    n = jnp.sum(mask)
    rank = jnp.ceil((n + 1) * (1 - alpha))
    ordered = jnp.sort(jnp.where(mask, scores, jnp.inf))
    index = jnp.clip(rank.astype(jnp.int32) - 1, 0, scores.shape[0] - 1)
    return jnp.where(rank > n, jnp.inf, ordered[index])


# ACI -----------------------------------------------------------------------------------------


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
    count: jax.Array
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

    init(dtype=None) -> ACIState: level alpha, no scores, radius +inf (nothing seen yet).
    update(state, scores (B,), mask (B,) = None, radius_in_force = None) -> (state, radius):
      each valid score misses when it is above the radius in force (`state.radius`, or
      `radius_in_force`, () or (B,), the radii issued with the predictions these scores
      belong to, for delayed feedback: `DelayedScores.issued`); level += gamma (alpha - miss)
      for each of them (sequential) or gamma (alpha - mean miss) once (mean); the valid
      scores enter the window in order, each pushing out the oldest once it is full;
      radius = the (1 - level) quantile of the window. Scores must be finite where valid. No
      valid score: nothing changes.

    The window is kept sorted as well, one score in and one out in O(W) each, so that an
    update costs O(B W), not a sort of W (measured: benchmarks/bench_conformal.py).
    """
    _check_alpha(alpha)
    if window < 1 or batch not in BATCH_MODES:
        raise ValueError(f"window must be >= 1 (got {window}) and batch one of {BATCH_MODES} "
                         f"(got {batch!r})")

    def init(dtype=None) -> ACIState:
        level = jnp.asarray(alpha, dtype or float)
        return ACIState(level=level, radius=jnp.asarray(jnp.inf, level.dtype),
                        scores=jnp.zeros((window,), level.dtype),
                        ordered=jnp.full((window,), jnp.inf, level.dtype),
                        count=jnp.zeros((), jnp.int32), head=jnp.zeros((), jnp.int32))

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

    def update(state: ACIState, scores: jax.Array, mask: jax.Array | None = None,
               radius_in_force: jax.Array | None = None) -> tuple[ACIState, jax.Array]:
        scores, mask = _scores_and_mask(scores, mask, state.scores.dtype)
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


# DtACI ---------------------------------------------------------------------------------------


class DtACIState(NamedTuple):
    """One DtACI instance with K experts. thresholds: (K,) the experts' radii q_i (metres,
    unclipped); weights: (K,) w_i; probs: (K,) p_i = w_i / sum(w); expert: () int32, the drawn
    expert; radius: () the radius in force, clipped to [0, r_max]."""

    thresholds: jax.Array
    weights: jax.Array
    probs: jax.Array
    expert: jax.Array
    radius: jax.Array


def dtaci(alpha: float = 0.1, gammas=(0.05, 0.1, 0.2), eta: float = 2.72,
          sigma: float = 1 / 1000, loss: str = "consistent", output: str = "sample",
          r_max: float = float("inf"), batch: str = "sequential") -> OnlineConformal:
    """DtACI with experts holding radii, as GenSafeNav runs it (module docstring).

    alpha: target miscoverage; gammas: the experts' steps (metres); eta: the weights'
    learning rate; sigma: the fixed share; loss: "consistent" (pinball loss of the
    (1 - alpha) quantile) or "gensafenav" (`alpha u - min(u, 0)`); output: "sample" (the drawn
    expert's radius) or "mean" (sum p_i q_i); r_max: the output is clipped to [0, r_max]
    (GenSafeNav: 1 m); batch: "sequential" or "mean", how a batch of scores is taken.

    init(q0, dtype=None) -> DtACIState: every expert at q0, weights 1, radius clip(q0).
    update(state, scores (B,), mask (B,) = None, uniform = None) -> (state, radius): for each
      expert, u = s - q_i, l_i = loss(u), q_i <- q_i - gamma_i (alpha - 1{q_i < s});
      wbar_i = w_i exp(-eta l_i), w_i <- (1 - sigma) wbar_i / sum(wbar) + sigma / K,
      p = w / sum(w); then the expert is drawn from p with `uniform` (in [0, 1), one per
      update; unused for output="mean"). No valid score: nothing changes.
    """
    _check_alpha(alpha)
    if loss not in LOSSES or output not in OUTPUTS or batch not in BATCH_MODES:
        raise ValueError(f"loss must be one of {LOSSES} (got {loss!r}), output one of "
                         f"{OUTPUTS} (got {output!r}), batch one of {BATCH_MODES} "
                         f"(got {batch!r})")
    gammas = tuple(float(g) for g in gammas)
    num_experts = len(gammas)

    def pinball(u):
        if loss == "consistent":
            return (1 - alpha) * jnp.maximum(u, 0) + alpha * jnp.maximum(-u, 0)
        return alpha * u - jnp.minimum(u, 0)

    def reweigh(weights, losses):
        # exp(-eta (l - min l)): the same weights after normalising, and no underflow to an
        # all-zero sum (NaN) when every loss is large (a 40 m score in float32).
        bar = weights * jnp.exp(-eta * (losses - jnp.min(losses)))
        return (1 - sigma) * bar / jnp.sum(bar) + sigma / num_experts

    def radius_of(thresholds, probs, expert):
        chosen = thresholds[expert] if output == "sample" else jnp.sum(probs * thresholds)
        return jnp.clip(chosen, 0, r_max)

    def init(q0, dtype=None) -> DtACIState:
        q0 = jnp.asarray(q0, dtype or float)
        thresholds = jnp.full((num_experts,), q0, q0.dtype)
        probs = jnp.full((num_experts,), 1 / num_experts, q0.dtype)
        expert = jnp.zeros((), jnp.int32)
        return DtACIState(thresholds=thresholds, weights=jnp.ones((num_experts,), q0.dtype),
                          probs=probs, expert=expert,
                          radius=radius_of(thresholds, probs, expert))

    def update(state: DtACIState, scores: jax.Array, mask: jax.Array | None = None,
               uniform: jax.Array | None = None) -> tuple[DtACIState, jax.Array]:
        dtype = state.thresholds.dtype
        scores, mask = _scores_and_mask(scores, mask, dtype)
        if uniform is None:
            if output == "sample":
                raise ValueError('output="sample" draws an expert: pass a uniform in [0, 1)')
            uniform = 0.0
        steps = jnp.asarray(gammas, dtype)

        def one_score(carry, score_and_valid):
            thresholds, weights = carry
            score, valid = score_and_valid
            losses = pinball(score - thresholds)
            new_thresholds = thresholds - steps * (alpha - (thresholds < score).astype(dtype))
            new_weights = reweigh(weights, losses)
            return (jnp.where(valid, new_thresholds, thresholds),
                    jnp.where(valid, new_weights, weights)), None

        if batch == "sequential" and scores.shape[0] == 1:
            (thresholds, weights), _ = one_score((state.thresholds, state.weights),
                                                 (scores[0], mask[0]))
        elif batch == "sequential":
            (thresholds, weights), _ = jax.lax.scan(
                one_score, (state.thresholds, state.weights), (scores, mask))
        else:
            count = jnp.maximum(jnp.sum(mask), 1)
            u = scores[:, None] - state.thresholds[None, :]                      # (B, K)
            losses = jnp.sum(jnp.where(mask[:, None], pinball(u), 0), axis=0) / count
            misses = jnp.sum(mask[:, None] & (state.thresholds[None, :] < scores[:, None]),
                             axis=0) / count
            thresholds = state.thresholds - steps * (alpha - misses.astype(dtype))
            weights = reweigh(state.weights, losses)
        any_valid = jnp.any(mask)
        thresholds = jnp.where(any_valid, thresholds, state.thresholds)
        weights = jnp.where(any_valid, weights, state.weights)
        probs = jnp.where(any_valid, weights / jnp.sum(weights), state.probs)
        cdf = jnp.cumsum(probs)
        drawn = jnp.searchsorted(cdf / cdf[-1], jnp.asarray(uniform, dtype), side="right")
        drawn = jnp.minimum(drawn, num_experts - 1).astype(jnp.int32)
        expert = jnp.where(any_valid, drawn, state.expert) if output == "sample" else \
            state.expert
        radius = radius_of(thresholds, probs, expert)
        return DtACIState(thresholds=thresholds, weights=weights, probs=probs, expert=expert,
                          radius=radius), radius

    return OnlineConformal(init, update)


# Delayed scores ------------------------------------------------------------------------------


class ScoreBufferState(NamedTuple):
    """The last P predictions of N track slots, a ring over time. predicted: (P, N, P, 2),
    [time slot, track, horizon step, xy]; valid: (P, N); issued: (P, N, P), what the caller
    issued with each prediction (e.g. its radii); step: () int32, updates so far."""

    predicted: jax.Array
    valid: jax.Array
    issued: jax.Array
    step: jax.Array


class DelayedScores(NamedTuple):
    """What one step's observations score. scores: (N, P), [track, k - 1], the distance of the
    horizon-k prediction made k steps ago to the position observed now (0 where masked);
    mask: (N, P); issued: (N, P), what was issued with that prediction (its radius;
    0 where masked)."""

    scores: jax.Array
    mask: jax.Array
    issued: jax.Array


def score_buffer_init(num_tracks: int, horizon: int, dtype=None) -> ScoreBufferState:
    """An empty buffer for `num_tracks` slots and `horizon` (P) predicted steps."""
    dtype = jnp.zeros((), dtype or float).dtype
    return ScoreBufferState(
        predicted=jnp.zeros((horizon, num_tracks, horizon, 2), dtype),
        valid=jnp.zeros((horizon, num_tracks), bool),
        issued=jnp.zeros((horizon, num_tracks, horizon), dtype),
        step=jnp.zeros((), jnp.int32))


def score_buffer_update(state: ScoreBufferState, predicted: jax.Array, valid: jax.Array,
                        observed: jax.Array, detected: jax.Array
                        ) -> tuple[ScoreBufferState, DelayedScores]:
    """One time step: score the positions `observed` (N, 2) (`detected` (N,); NaN allowed where
    not detected) against the predictions made 1..P steps ago, then keep this step's
    `predicted` (N, P, 2) (`valid` (N,): which tracks were predicted), to be scored over the
    next P steps; what is issued with it is 0 until `record_issued`."""
    horizon = state.predicted.shape[0]
    dtype = state.predicted.dtype
    ks = jnp.arange(1, horizon + 1)
    slots = (state.step - ks) % horizon                       # where the prediction of t - k is
    past = state.predicted[slots, :, ks - 1]                  # (P, N, 2): horizon k of t - k
    observed = jnp.asarray(observed, dtype)
    mask = state.valid[slots] & jnp.asarray(detected, bool)[None]             # (P, N)
    distance = jnp.linalg.norm(past - observed[None], axis=-1)
    issued = jnp.where(mask, state.issued[slots, :, ks - 1], 0)
    delayed = DelayedScores(scores=jnp.where(mask, distance, 0).T, mask=mask.T,
                            issued=issued.T)
    slot = state.step % horizon
    state = ScoreBufferState(
        predicted=state.predicted.at[slot].set(jnp.asarray(predicted, dtype)),
        valid=state.valid.at[slot].set(jnp.asarray(valid, bool)),
        issued=state.issued.at[slot].set(0),
        step=state.step + 1)
    return state, delayed


def record_issued(state: ScoreBufferState, issued: jax.Array) -> ScoreBufferState:
    """Keep `issued` (N, P) (the radii given out with the prediction the last update stored,
    once the conformal update of that step has made them), to come back with its scores as
    `DelayedScores.issued`: the radius in force for ACI's `radius_in_force`."""
    slot = (state.step - 1) % state.predicted.shape[0]
    return state._replace(issued=state.issued.at[slot].set(
        jnp.asarray(issued, state.issued.dtype)))


def reset_slots(state: ScoreBufferState, slots: jax.Array) -> ScoreBufferState:
    """Forget the past predictions of the track slots where `slots` (N,) is true (a slot
    given to a new person): their scores stay masked until it has been predicted anew."""
    return state._replace(valid=state.valid & ~jnp.asarray(slots, bool)[None])
