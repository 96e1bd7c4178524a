"""Delayed feedback: the score of a k-step-ahead prediction is known k steps later.

`score_buffer_init` / `score_buffer_update` turn a stream of predictions and observations
into the delayed scores: at each step, for k = 1..P, the horizon-k score of the prediction
made k steps earlier, masked where that track's prediction was not valid then or the track is
not detected now; `record_issued` keeps the radii given out with a prediction, which come
back with its scores (`update`'s `radius_in_force`, for the coverage of the discs actually
used). Track slots are fixed: a slot given to a new person must be cleared with `reset_slots`
(and its per-track conformal state re-initialised by the caller).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp


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
    `DelayedScores.issued`: the radius in force, `update`'s `radius_in_force`."""
    slot = (state.step - 1) % state.predicted.shape[0]
    return state._replace(issued=state.issued.at[slot].set(
        jnp.asarray(issued, state.issued.dtype)))


def reset_slots(state: ScoreBufferState, slots: jax.Array) -> ScoreBufferState:
    """Forget the past predictions of the track slots where `slots` (N,) is true (a slot
    given to a new person): their scores stay masked until it has been predicted anew."""
    return state._replace(valid=state.valid & ~jnp.asarray(slots, bool)[None])
