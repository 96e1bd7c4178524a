"""A stream's step without its compiled program, in numpy on the host: constant velocity for a
frame the model cannot predict in time (`gst_jax.stream.Stream`: its program for a new capacity
still compiling, its step past the deadline or failed).

    state = observe(state, ids, positions, lost, gate)        # the tracks move on, as the core's
    state = skip_scoring(state, regions, fresh_regions)        # nothing issued, nothing scored
    futures, predicted = constant_velocity(state, pred_len)    # (1, P, C, 2), (C,)

The tracks are kept exactly as the core's `observe` keeps them (its test holds the two equal),
so that the compiled program takes over with every history whole. The score buffer and the
online correction record a step at which nothing was issued: the model's earlier predictions
that mature at it go unscored and the conformal states do not move (a new track's per-slot
state starts afresh, as the core's would); the discs given out are the radii in force.
Everything here is numpy (jax only walks the pytrees): it runs where the device is busy with
the step that overran, or has failed.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from gst_jax import conformal
from gst_jax.conformal import Regions
from gst_jax.stream_core import FREE, Gate, StreamState


def observe(state: StreamState, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray,
            gate: Gate | None = None) -> StreamState:
    """`gst_jax.stream_core.observe` on a state of numpy arrays, for a frame of ids (M,)
    (no FREE among them), positions (M, 2) and lost ids (L,); gate in metres and model steps
    (`Gate.in_steps`). The same slots, histories and flags, bit for bit."""
    ids = np.asarray(ids, np.int32)
    history = np.roll(np.asarray(state.positions), -1, axis=-2)
    history[..., -1, :] = 0.0
    detected = np.roll(np.asarray(state.detected), -1, axis=-1)
    detected[..., -1] = 0.0
    track_ids = np.where(detected.any(axis=-1), np.asarray(state.track_ids), FREE)
    gone = (track_ids != FREE) & np.isin(track_ids, lost)
    track_ids = np.where(gone, FREE, track_ids)

    same = track_ids[:, None] == ids[None, :]                                  # (C, M)
    new = ~same.any(axis=0)
    free = track_ids == FREE
    # The k-th new id takes the k-th free slot.
    taken = free[:, None] & new[None, :] & (
        (np.cumsum(free) - 1)[:, None] == (np.cumsum(new) - 1)[None, :])
    slot_of = same | taken
    written = slot_of.any(axis=1)
    track_ids = np.where(taken.any(axis=1), (taken * ids[None, :]).sum(axis=1),
                         track_ids).astype(np.int32)
    newest = (slot_of[..., None] * np.asarray(positions, np.float32)[None]).sum(axis=1)
    restarted = np.zeros(track_ids.shape, bool)
    if gate is not None:
        steps = np.arange(detected.shape[-1])
        seen = detected > 0
        last = np.max(np.where(seen, steps, -1), axis=-1)                        # (C,)
        before = np.max(np.where(seen & (steps < last[:, None]), steps, -1), axis=-1)
        last_xy, before_xy = _at(history, last), _at(history, before)
        has_velocity = before >= 0
        gaps = np.maximum(last - before, 1).astype(np.float32)
        velocity = np.where(has_velocity[:, None], (last_xy - before_xy) / gaps[:, None],
                            np.float32(0))
        elapsed = (steps[-1] - last).astype(np.float32)
        restarted = same.any(axis=1) & gate.another_person(last_xy, velocity, has_velocity,
                                                           newest, elapsed)
    # A slot given to another person starts empty.
    cleared = taken.any(axis=1) | gone | restarted
    history = np.where(cleared[:, None, None], np.float32(0), history)
    detected = np.where(cleared[:, None], np.float32(0), detected)
    history[:, -1] = np.where(written[:, None], newest, np.float32(0))
    detected[:, -1] = written
    dropped = np.asarray(state.dropped) + np.int32((new & ~taken.any(axis=0)).sum())
    return state.replace(track_ids=track_ids, positions=history, detected=detected,
                         dropped=dropped.astype(np.int32), fresh=cleared, restarted=restarted)


def _at(history: np.ndarray, step: np.ndarray) -> np.ndarray:
    """(C, 2) each slot's position at its `step` (C,) of the history (C, T, 2) (0 for -1)."""
    return np.take_along_axis(history, np.maximum(step, 0)[:, None, None], axis=-2)[:, 0]


def skip_scoring(state: StreamState, regions: Regions | None, fresh_regions) -> StreamState:
    """The score buffer and the online correction one step on, at which nothing was issued
    (the slots `state.fresh` forgotten first, as the core's step forgets them), the per-slot
    conformal states of fresh slots started afresh from `fresh_regions` (one slot's, leading
    axis 1); the pooled conformal state and the correction's statistics unchanged."""
    fresh = np.asarray(state.fresh)
    if state.adaptation is not None:             # a ring of the last P issues, newest last
        ring: Any = jax.tree.map(np.asarray, state.adaptation.issued)
        ring = ring._replace(valid=ring.valid & ~fresh[None])
        ring = jax.tree.map(lambda rows: np.concatenate([rows[1:], np.zeros_like(rows[:1])]),
                            ring)
        state = state.replace(adaptation=state.adaptation._replace(issued=ring))
    if state.feed is None:
        return state
    feed: Any = jax.tree.map(np.array, state.feed)          # copies, written here
    slot = int(feed.step) % feed.valid.shape[0]             # this step's row of the ring
    feed.valid[:, fresh] = False
    feed.valid[slot], feed.predicted[slot], feed.issued[slot] = False, 0, 0
    state = state.replace(feed=feed._replace(step=(feed.step + 1).astype(np.int32)))
    if regions is not None and not regions.pooled and state.regions is not None:
        state = state.replace(regions=_where_slots(fresh, fresh_regions, state.regions))
    return state


def _where_slots(slots: np.ndarray, fresh, old):
    """Per slot (leading axis C), `fresh` (leading axis 1) where `slots` (C,), else `old`."""
    return jax.tree.map(lambda f, o: np.where(slots.reshape((-1,) + (1,) * (np.ndim(o) - 1)),
                                              f, o), fresh, old)


def constant_velocity(state: StreamState, pred_len: int, samples: int = 1
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Each slot's last displacement repeated: futures (samples, P, C, 2) float32 and
    predicted (C,), the slots detected at both of the last two steps (as
    `gst_jax.predictors.ConstantVelocity`)."""
    positions = np.asarray(state.positions)
    now, last = positions[:, -1], positions[:, -1] - positions[:, -2]
    steps = np.arange(1, pred_len + 1, dtype=np.float32)[:, None, None]
    futures = (now[None] + steps * last[None]).astype(np.float32)               # (P, C, 2)
    predicted = np.asarray((np.asarray(state.detected)[:, -2:] > 0).all(axis=-1))
    return np.broadcast_to(futures, (samples, *futures.shape)), predicted


def radii_in_force(state: StreamState, regions: Regions | None, pred_len: int
                   ) -> np.ndarray | None:
    """(C, P) the radii the conformal states hold now (those last issued; infinite without a
    method), None without regions."""
    if regions is None:
        return None
    shape = (state.capacity, pred_len)
    if state.regions is None:
        return np.full(shape, np.inf, np.float32)
    return np.broadcast_to(np.asarray(state.regions.radius, np.float32), shape).copy()


def nothing_scored(capacity: int, pred_len: int) -> conformal.DelayedScores:
    """The delayed scores of a step that scored nothing: (C, P), all masked."""
    zeros: Any = np.zeros((capacity, pred_len), np.float32)
    return conformal.DelayedScores(zeros, zeros > 0, zeros)
