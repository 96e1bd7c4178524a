"""DtACI: experts that track radii, weighted by their losses (GenSafeNav's port).

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
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gst_jax.conformal._src.base import (
    BATCH_MODES,
    LOSSES,
    OUTPUTS,
    OnlineConformal,
    check_alpha,
    scores_and_mask,
)
from gst_jax.conformal._src.split import start_radius


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
    """DtACI with experts holding radii, as GenSafeNav runs it (this module's docstring).

    alpha: target miscoverage; gammas: the experts' steps (metres); eta: the weights'
    learning rate; sigma: the fixed share; loss: "consistent" (pinball loss of the
    (1 - alpha) quantile) or "gensafenav" (`alpha u - min(u, 0)`); output: "sample" (the drawn
    expert's radius) or "mean" (sum p_i q_i); r_max: the output is clipped to [0, r_max]
    (GenSafeNav: 1 m); batch: "sequential" or "mean", how a batch of scores is taken.

    init(initial_radius=None, *, scores=None, dtype=None) -> DtACIState: every expert at
      q0 = `initial_radius` (0 for None), weights 1, radius clip(q0); given calibration
      scores (n,), q0 is their split-conformal radius (`split_radius`: the
      ceil((n+1)(1-alpha))-th smallest), or `initial_radius` where they are too few for the
      level.
    update(state, scores (B,), mask (B,) = None, *, radius_in_force = None, uniform = None)
      -> (state, radius): for each expert, u = s - q_i, l_i = loss(u), q_i <- q_i - gamma_i
      (alpha - 1{q_i < s}); wbar_i = w_i exp(-eta l_i), w_i <- (1 - sigma) wbar_i / sum(wbar)
      + sigma / K, p = w / sum(w); then the expert is drawn from p with `uniform` (in [0, 1),
      one per update; unused for output="mean"). No valid score: nothing changes.
      `radius_in_force` is accepted for the common signature and unused: each expert is
      judged by its own radius.
    """
    check_alpha(alpha)
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

    def init(initial_radius=None, *, scores: jax.Array | None = None, dtype=None
             ) -> DtACIState:
        q0 = start_radius(alpha, initial_radius, scores, dtype)
        thresholds = jnp.full((num_experts,), q0, q0.dtype)
        probs = jnp.full((num_experts,), 1 / num_experts, q0.dtype)
        expert = jnp.zeros((), jnp.int32)
        return DtACIState(thresholds=thresholds, weights=jnp.ones((num_experts,), q0.dtype),
                          probs=probs, expert=expert,
                          radius=radius_of(thresholds, probs, expert))

    def update(state: DtACIState, scores: jax.Array, mask: jax.Array | None = None, *,
               radius_in_force: jax.Array | None = None,
               uniform: jax.Array | float | None = None) -> tuple[DtACIState, jax.Array]:
        dtype = state.thresholds.dtype
        scores, mask = scores_and_mask(scores, mask, dtype)
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
