"""The stream's pure core: a tracker's frames in, every track's predictions out, as functions
of arrays that jit, vmap over robots (environments, as CrowdNav++ trains) and run inside a
planner's program. `gst_jax.stream` holds its host class, `Stream` (numpy in and out, ids in
any order, capacity growth, times, compiling ahead), and re-exports every name of this module:
users import them from there; the navigation environment, which needs no host, imports this.

    state = init_state(capacity, obs_len)               # StreamState
    state = observe(state, frame, gate)                  # Frame: ids (M,), positions (M, 2)
    futures, predicted = predict_slots(model, params, key, state)
    step = make_step(model, regions, gate=Gate(...))     # all of it: jit it, vmap it

Each track keeps its last `obs_len` positions with a detection mask in one of the state's C
slots, as a window's pedestrians do: a track that appears is partially detected, one unseen
for `obs_len` steps frees its slot for reuse, a lost id (`Frame.lost`) frees it at once, and
a known id whose detection is another person's by the `Gate` (too far from where its recent
velocity would have carried it, or beyond any speed) restarts its track in its slot. A new
track that finds no free slot is refused and counted (`StreamState.dropped`): the host grows
the capacity and steps again. Steps where nobody was detected (a gap in the tracker's frames)
run without the model (`make_step`'s idle). With `adaptation` (`gst_jax.adaptation`) the
predictions are corrected online from their delayed scores (`adapt`); with `regions` the
earlier predictions are scored against the positions observed now and conformal discs issued
(`update_regions`).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import flax
import jax
import jax.numpy as jnp

from gst_jax import conformal, predictors
from gst_jax.adaptation import Adaptation, AdaptationState
from gst_jax.arrays import BatchArray
from gst_jax.conformal import Regions
from gst_jax.data import SceneBatch
from gst_jax.model import Params
from gst_jax.predictors import GST, Predictor, last_two_detected

# The id of a free slot; track ids are 0 or more (int32).
FREE = -1


class StreamState(flax.struct.PyTreeNode):
    """The tracks a stream holds, in C slots (any leading axes: robots).

    track_ids: (C,) int32, FREE for a free slot.
    positions: (C, T, 2) float32 metres, the last T = obs_len steps, oldest first; 0 where
      not detected.
    detected: (C, T) float32, 1 where the track was detected.
    dropped: () int32, new tracks refused so far for want of a free slot (the host grows
      the capacity and steps again when it rises).
    fresh: (C,) bool, the slots whose history and pending predictions belong to no track of
      before the last `observe`: a new track took the slot, the track was forgotten
      (`Frame.lost`) or restarted.
    restarted: (C,) bool, the slots whose track was restarted at the last `observe`: its id
      reappeared where its track could not have gone (`observe`'s gate).
    feed: the last P predictions of every slot, scored as the future is observed
      (`conformal.ScoreBufferState`), or None without regions.
    regions: the conformal state of the regions (`gst_jax.conformal.Regions`): one
      instance per horizon step (pooled), or per slot and horizon step; None without.
    adaptation: the online correction's state (`gst_jax.adaptation`), or None without.
    """

    track_ids: jax.Array
    positions: jax.Array
    detected: jax.Array
    dropped: jax.Array
    fresh: jax.Array
    restarted: jax.Array
    feed: conformal.ScoreBufferState | None = None
    regions: Any = None                 # the method's own state (ACIState, DtACIState, ...)
    adaptation: AdaptationState | None = None

    @property
    def capacity(self) -> int:
        return self.track_ids.shape[-1]


class Frame(NamedTuple):
    """The people detected in one frame: ids (M,) int32 (FREE pads), positions (M, 2); lost:
    (L,) int32 the ids whose tracks end before this frame's detections are matched (FREE
    pads; an id among them that is also detected now starts a new track), or None."""

    ids: BatchArray
    positions: BatchArray
    lost: BatchArray | None = None


class Gate(NamedTuple):
    """When a known id's new detection is another person's (a recycled id, a tracker's
    switch), in metres and seconds (or, for `observe`, metres and model steps: `in_steps`).

    max_speed: nobody moves faster: a detection farther than max_speed x elapsed from the
      track's last detected position is another person's.
    max_acceleration, tolerance: a track detected at least twice moves on at the velocity of
      its last two detections, give or take tolerance + max_acceleration x elapsed^2 / 2 (a
      tracker's noise, a person speeding up, slowing down or turning): a detection farther
      from there is another person's. None: the speed rule alone.
    """

    max_speed: float
    max_acceleration: float | None = None
    tolerance: float = 0.0

    def in_steps(self, step_s: float) -> Gate:
        """The same gate in metres and steps of `step_s` seconds."""
        return Gate(self.max_speed * step_s, None if self.max_acceleration is None
                    else self.max_acceleration * step_s ** 2, self.tolerance)

    def another_person(self, last, velocity, has_velocity, newest, elapsed):
        """(...,) whether each detection `newest` (..., 2) is another person's than the track
        last detected at `last` (..., 2), `elapsed` (...,) ago, moving at `velocity` (..., 2)
        where `has_velocity` (...,). numpy or jax arrays alike (the host's raw frames, the
        core's steps)."""
        another = _length(newest - last) > self.max_speed * elapsed
        if self.max_acceleration is None:
            return another
        deviation = _length(newest - last - velocity * elapsed[..., None])
        allowed = self.tolerance + self.max_acceleration * elapsed ** 2 / 2
        return another | (has_velocity & (deviation > allowed))


def _length(vectors):
    """(...,) the lengths of (..., 2) vectors, numpy or jax."""
    return ((vectors * vectors).sum(axis=-1)) ** 0.5


def init_state(capacity: int, obs_len: int, regions: Regions | None = None,
               pred_len: int = 0, adaptation: Adaptation | None = None) -> StreamState:
    """An empty stream of `capacity` slots (with `regions` or `adaptation`: of `pred_len`
    predicted steps)."""
    state = StreamState(track_ids=jnp.full((capacity,), FREE, jnp.int32),
                        positions=jnp.zeros((capacity, obs_len, 2), jnp.float32),
                        detected=jnp.zeros((capacity, obs_len), jnp.float32),
                        dropped=jnp.zeros((), jnp.int32),
                        fresh=jnp.zeros((capacity,), bool),
                        restarted=jnp.zeros((capacity,), bool))
    if adaptation is not None:
        state = state.replace(adaptation=adaptation.init(capacity, pred_len))
    if regions is None:
        return state
    return state.replace(feed=conformal.score_buffer_init(capacity, pred_len, jnp.float32),
                         regions=regions.init(capacity, pred_len))


def observe(state: StreamState, frame: Frame, gate: Gate | float | None = None
            ) -> StreamState:
    """The state one step later: every slot's history moves back a step, the tracks of the
    frame's lost ids and those unseen for all T steps free their slots, and the frame's people
    are written at the newest step (a known id into its slot, a new id into a free slot in
    the order of the frame).

    gate: in metres and model steps (`Gate.in_steps`). A known id whose detection the gate
    judges another person's restarts its track in its slot (the history is cleared: it is
    another person under a recycled id); its velocity is that of its last two detections in
    the history, its elapsed time the steps since the last. A number: metres per step, the
    speed rule alone (`Gate(max_jump)`); None: never."""
    ids = jnp.asarray(frame.ids, jnp.int32)
    positions = jnp.roll(state.positions, -1, axis=-2).at[..., -1, :].set(0.0)
    detected = jnp.roll(state.detected, -1, axis=-1).at[..., -1].set(0.0)
    track_ids = jnp.where(detected.any(axis=-1), state.track_ids, FREE)
    lost = jnp.zeros(track_ids.shape, bool)
    if frame.lost is not None:
        gone = jnp.asarray(frame.lost, jnp.int32)
        lost = ((track_ids[:, None] == gone[None, :]) & (gone != FREE)[None, :]).any(axis=1)
        lost &= track_ids != FREE
        track_ids = jnp.where(lost, FREE, track_ids)

    present = ids != FREE                                                       # (M,)
    same = (track_ids[:, None] == ids[None, :]) & present[None, :]              # (C, M)
    new = present & ~same.any(axis=0)
    free = track_ids == FREE
    # The k-th new id takes the k-th free slot.
    new_rank = jnp.cumsum(new) - 1
    free_rank = jnp.cumsum(free) - 1
    taken = free[:, None] & new[None, :] & (free_rank[:, None] == new_rank[None, :])
    slot_of = same | taken                                                      # (C, M)
    written = slot_of.any(axis=1)
    track_ids = jnp.where(taken.any(axis=1), (taken * ids[None, :]).sum(axis=1), track_ids)
    xy = jnp.asarray(frame.positions, jnp.float32)
    newest = (slot_of[..., None] * xy[None]).sum(axis=1)                        # (C, 2)
    restarted = jnp.zeros(track_ids.shape, bool)
    if gate is not None:
        gate = gate if isinstance(gate, Gate) else Gate(gate)
        steps = jnp.arange(detected.shape[-1])
        seen = detected > 0
        # Each slot's last two detected steps in its history (-1: none).
        last = jnp.max(jnp.where(seen, steps, -1), axis=-1)                     # (C,)
        before = jnp.max(jnp.where(seen & (steps < last[:, None]), steps, -1), axis=-1)
        at = lambda step: jnp.take_along_axis(positions, jnp.maximum(step, 0)[:, None, None],
                                              axis=-2)[:, 0]
        last_xy, before_xy = at(last), at(before)
        has_velocity = before >= 0
        velocity = jnp.where(has_velocity[:, None], (last_xy - before_xy)
                             / jnp.maximum(last - before, 1)[:, None], 0.0)
        elapsed = (steps[-1] - last).astype(jnp.float32)
        restarted = same.any(axis=1) & gate.another_person(last_xy, velocity, has_velocity,
                                                           newest, elapsed)
    # A slot given to another person starts empty.
    cleared = taken.any(axis=1) | lost | restarted
    positions = jnp.where(cleared[:, None, None], 0.0, positions)
    detected = jnp.where(cleared[:, None], 0.0, detected)
    positions = positions.at[:, -1].set(jnp.where(written[:, None], newest, 0.0))
    detected = detected.at[:, -1].set(written.astype(jnp.float32))
    dropped = state.dropped + (new & ~taken.any(axis=0)).sum().astype(jnp.int32)
    return state.replace(track_ids=track_ids, positions=positions, detected=detected,
                         dropped=dropped, fresh=cleared, restarted=restarted)


def as_batch(state: StreamState) -> SceneBatch:
    """The state as a one-scene batch of the model's (T = obs_len observed steps)."""
    return predictors.as_batch(state.positions, state.detected)


def update_regions(regions: Regions, state: StreamState, key: jax.Array,
                   new_slots: jax.Array, futures: jax.Array, predicted: jax.Array
                   ) -> tuple[StreamState, jax.Array, conformal.DelayedScores]:
    """Score the predictions of 1..P steps ago against the positions observed now, update
    the radii (`Regions.advance`; the `new_slots` (C,) start afresh), and keep this step's
    predictions (futures (K, P, C, 2), predicted (C,)). Returns the state, the radii issued
    with this step's predictions (C, P) and the delayed scores (scores, mask, issued:
    (C, P))."""
    assert state.feed is not None, "a state made with regions (init_state) has a feed"
    feed = conformal.reset_slots(state.feed, new_slots)
    mean = jnp.moveaxis(futures.mean(axis=0), 1, 0)                           # (C, P, 2)
    feed, delayed = conformal.score_buffer_update(
        feed, mean, predicted > 0, state.positions[:, -1], state.detected[:, -1] > 0)
    regions_state, radii = regions.advance(state.regions, key, new_slots, delayed)
    feed = conformal.record_issued(feed, radii)
    return state.replace(feed=feed, regions=regions_state), radii, delayed


# What a stream predicts with: any `gst_jax.predictors.Predictor`; a model's is `GST`.
StreamModel = GST


def predict_slots(model: Predictor, params: Params | None, key: jax.Array, state: StreamState
                  ) -> tuple[jax.Array, jax.Array]:
    """Every slot's future from its history: (futures (K, P, C, 2), predicted (C,)), where
    predicted marks the tracks the model predicts (the others' futures are meaningless)."""
    return model.predict(params, key, state.positions, state.detected)


def adapt(adaptation: Adaptation, state: StreamState, futures: jax.Array, predicted: jax.Array
          ) -> tuple[StreamState, jax.Array]:
    """Score the raw predictions of 1..P steps ago against the positions observed now,
    correct this step's futures (K, P, C, 2) (`gst_jax.adaptation`) and keep them raw."""
    now, seen = state.positions[:, -1], state.detected[:, -1] > 0
    moved = last_two_detected(state.detected)
    last_step = jnp.where(moved[:, None], now - state.positions[:, -2], 0.0)
    assert state.adaptation is not None, "a state made with an adaptation (init_state)"
    adapted_state = adaptation.observe(adaptation.reset_slots(state.adaptation, state.fresh),
                                       now, seen)
    per_slot = lambda sample: jnp.moveaxis(sample, 1, 0)                      # (C, P, 2)
    adapted = jax.vmap(lambda sample: per_slot(adaptation.apply(
        adapted_state, now, per_slot(sample), last_step)))(futures)
    adapted_state = adaptation.issue(adapted_state, now, per_slot(futures.mean(axis=0)),
                                     last_step, predicted > 0)
    return state.replace(adaptation=adapted_state), adapted


def make_step(model: Predictor, regions: Regions | None = None, *,
              max_speed: float | None = None, step_s: float | None = None,
              adaptation: Adaptation | None = None, gate: Gate | None = None) -> Callable:
    """The pure `step(params, state, frame, key, idle=0) -> (state, futures, predicted, radii,
    delayed)`: observe the frame, predict every slot (`predict_slots`), with `adaptation`
    correct the predictions from their delayed scores (`adapt`), and with `regions` score the
    earlier predictions and issue this step's radii (C, P) (`update_regions`; without, radii
    and delayed are None). jit it, vmap it over robots.

    gate (metres and seconds, `step_s` seconds a step, default: the model's): a known id
    whose detection it judges another person's starts a new track (`observe`); max_speed
    (m/s) alone is `Gate(max_speed)`; neither: never.
    idle: that many steps where nobody was detected come first (a gap in a tracker's frames,
    a traced int32 or 0), each observed, adapted and scored as a step of an empty frame, the
    frame's lost ids ending their tracks at the first, without running the model: nobody is
    predicted at a step where they were not detected."""
    if max_speed is not None:
        if gate is not None:
            raise ValueError("make_step: give max_speed or gate, not both")
        gate = Gate(max_speed)
    if gate is not None:
        if not step_s:              # the model's step; a predictor without a model has none
            if not isinstance(model, GST):
                raise ValueError("make_step: a gate needs step_s where the predictor has no "
                                 "model (its step)")
            step_s = model.config.step_s
        gate = gate.in_steps(step_s)

    def idle_step(index: jax.Array, state: StreamState, lost: BatchArray | None,
                  key: jax.Array) -> StreamState:
        capacity = state.capacity
        empty = Frame(jnp.full((capacity,), FREE, jnp.int32),
                      jnp.zeros((capacity, 2), jnp.float32), lost)
        state = observe(state, empty, gate)
        # What the model would predict is never read: no slot is predicted (nor scored
        # against) where nobody was detected now.
        futures = jnp.zeros((1, model.pred_len, capacity, 2), jnp.float32)
        predicted = jnp.zeros((capacity,), bool)
        if adaptation is not None:
            state, _ = adapt(adaptation, state, futures, predicted)
        if regions is not None:
            regions_key = jax.random.split(jax.random.fold_in(key, index))[1]
            state, _, _ = update_regions(regions, state, regions_key, state.fresh, futures,
                                         predicted)
        return state

    def step(params: Params | None, state: StreamState, frame: Frame, key: jax.Array,
             idle: jax.Array | int = 0):
        if not (isinstance(idle, int) and idle == 0):
            state = jax.lax.fori_loop(
                0, idle, lambda i, s: idle_step(i, s, frame.lost, key), state)
        state = observe(state, frame, gate)
        predict_key, regions_key = jax.random.split(key)
        futures, predicted = predict_slots(model, params, predict_key, state)
        if adaptation is not None:
            state, futures = adapt(adaptation, state, futures, predicted)
        if regions is None:
            return state, futures, predicted, None, None
        state, radii, delayed = update_regions(regions, state, regions_key, state.fresh,
                                               futures, predicted)
        return state, futures, predicted, radii, delayed
    return step
