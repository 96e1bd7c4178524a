"""Conformal PID control without a scorecaster: quantile tracking plus an error integrator.

**PID** (`pid`; Angelopoulos, Candès & Tibshirani 2023, "Conformal PID control for time
series prediction"): the radius is

    q_{t+1} = p_{t+1} + r_t(S_t),   p_{t+1} = p_t + eta (err_t - alpha),
    S_t = sum_{i<=t} (err_i - alpha)

with err_t = 1{s_t > q_t} (the radius the score's prediction was issued with). p is quantile
tracking (the P part: on its own, |(1/T) sum err_t - alpha| <= (B + eta)/(eta T) for scores
in [0, B] and p_1 in [0, B]); the integrator (the I part) is the saturation function
r_t(x) = K_I tan(x log(t) / (t C_sat)), with tan(x) = sign(x) inf outside (-pi/2, pi/2):
once the misses exceed alpha t by (pi/2) C_sat t / log(t), every radius is infinite until
they no longer do (and the empty disc on the other side), so whatever the scores,
|(1/T) sum err_t - alpha| <= (pi/2) C_sat / log(T) + (d + 1)/T with feedback d scores late
(the paper's Proposition with h(t) = t / log(t)). The scorecaster (the D part) is left out:
a trajectory's score has no useful forecast beyond what the predictor already gave. The
disc's radius is q clipped to [0, inf]; p and S are kept unclipped.

With delayed feedback (the horizon-k score of a prediction comes back k steps later),
`radius_in_force` gives each score's err against the radius issued with it, as for ACI. A
batch of scores (pooled) is taken one score at a time, in order (`batch="sequential"` of the
other methods): t counts scores.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gst_jax.conformal._src.base import OnlineConformal, check_alpha, scores_and_mask
from gst_jax.conformal._src.split import start_radius


class PIDState(NamedTuple):
    """One PID instance. tracking: () p_t, the quantile-tracking part (metres); misses: ()
    S_t = sum of (err_i - alpha); count: () int32, t, the scores taken; radius: () the radius
    in force, max(p_t + r_t(S_t), 0)."""

    tracking: jax.Array
    misses: jax.Array
    count: jax.Array  # type: ignore[assignment]  # shadows tuple.count (mypy: an override)
    radius: jax.Array


def saturation(x: jax.Array, t: jax.Array, k_i: float, c_sat: float) -> jax.Array:
    """r_t(x) = K_I tan(x log(t) / (t C_sat)), +-inf where the argument leaves (-pi/2, pi/2);
    0 before any score (t = 0) and at t = 1 (log 1 = 0)."""
    t = jnp.maximum(t, 1).astype(x.dtype)
    argument = x * jnp.log(t) / (t * c_sat)
    inside = jnp.abs(argument) < math.pi / 2
    return jnp.where(inside, k_i * jnp.tan(jnp.where(inside, argument, 0)),
                     jnp.sign(argument) * jnp.inf)


def pid(alpha: float = 0.1, eta: float = 0.02, k_i: float = 1.0, c_sat: float = 10.0
        ) -> OnlineConformal:
    """Conformal PID control, P and I (this module's docstring). alpha: target miscoverage;
    eta: the quantile-tracking step (metres per miss); k_i: the integrator's gain (metres);
    c_sat: its saturation constant (the integrator makes every radius infinite once the
    misses exceed alpha by (pi/2) c_sat / log(t) of the scores). The defaults had the lowest
    coverage error without infinite radii on the scenes' validation streams
    (results/conformal_selection.md, `experiments/conformal_coverage.py --select`).

    init(initial_radius=None, *, scores=None, dtype=None) -> PIDState: p_1 = q0 =
      `initial_radius` (0 for None), no scores, radius max(q0, 0); given calibration scores
      (n,), q0 is their split-conformal radius (`split_radius`: the ceil((n+1)(1-alpha))-th
      smallest), or `initial_radius` where they are too few for the level.
    update(state, scores (B,), mask (B,) = None, *, radius_in_force = None, uniform = None)
      -> (state, radius): for each valid score in order, err = 1{s > radius in force}
      (`state.radius`, or `radius_in_force`, () or (B,), the radii issued with the
      predictions these scores belong to), p += eta (err - alpha), S += err - alpha, t += 1;
      then radius = max(p + r_t(S), 0). No valid score: nothing changes. `uniform` is
      accepted for the common signature and unused: PID draws nothing.
    """
    check_alpha(alpha)
    if not (eta > 0 and k_i > 0 and c_sat > 0):
        raise ValueError(f"eta, k_i and c_sat must be positive, got {eta}, {k_i}, {c_sat}")

    def radius_of(tracking, misses, count):
        return jnp.maximum(tracking + saturation(misses, count, k_i, c_sat), 0)

    def init(initial_radius=None, *, scores: jax.Array | None = None, dtype=None
             ) -> PIDState:
        tracking = start_radius(alpha, initial_radius, scores, dtype)
        misses = jnp.zeros((), tracking.dtype)
        count = jnp.zeros((), jnp.int32)
        return PIDState(tracking, misses, count, radius_of(tracking, misses, count))

    def update(state: PIDState, scores: jax.Array, mask: jax.Array | None = None, *,
               radius_in_force: jax.Array | None = None, uniform: jax.Array | None = None
               ) -> tuple[PIDState, jax.Array]:
        scores, mask = scores_and_mask(scores, mask, state.tracking.dtype)
        # The batch's radii were all issued before any of its scores came back.
        issued = jnp.broadcast_to(jnp.asarray(
            state.radius if radius_in_force is None else radius_in_force, scores.dtype),
            scores.shape)

        def one_score(carry, x):
            tracking, misses, count, _ = carry
            score, valid, in_force = x
            step = (score > in_force).astype(tracking.dtype) - alpha
            tracked = (tracking + eta * step, misses + step, count + 1)
            new = (*tracked, radius_of(*tracked))
            return tuple(jnp.where(valid, a, b) for a, b in zip(new, carry)), None

        carry = tuple(state)
        if scores.shape[0] == 1:
            carry, _ = one_score(carry, (scores[0], mask[0], issued[0]))
        else:
            carry, _ = jax.lax.scan(one_score, carry, (scores, mask, issued))
        state = PIDState(*carry)
        return state, state.radius

    return OnlineConformal(init, update)
