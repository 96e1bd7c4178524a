"""Prediction over a tracker's output, one frame at a time: what a robot runs.

    stream = Stream(load_model("pretrained:crowdnav_sim"))
    out = stream.step(track_ids, positions)             # the people detected now
    out.ids, out.futures                                 # (L,), (L, P, 2) or (L, K, P, 2)

Each track keeps its last `obs_len` positions with a detection mask in a slot of a fixed
capacity, as a window's pedestrians do: a track that appears is partially detected (GST's
point: it is predicted from the steps it was seen), one unseen for `obs_len` steps is dropped
and its slot reused. Capacity grows by the buckets of `gst_jax.data.bucket_size`, so a crowd
that changes size meets few compiled programs.

Underneath, everything is a pure function of arrays, so that it jits, vmaps over robots
(environments, as CrowdNav++ trains) and runs inside a planner's program:

    state = init_state(capacity, obs_len)               # StreamState
    state = observe(state, frame)                        # Frame: ids (M,), positions (M, 2)
    futures, predicted = predict_slots(model, key, state)

`Stream` is the convenience around them: numpy in and out, ids in any order, capacity
growth. The model is any gst_jax model (the paper's, `crowdnav_sim`, ...) or CrowdNav++'s
(`crowdnav.predict`, with its own input conventions).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import flax
import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import ModelConfig
from gst_jax import conformal, crowdnav
from gst_jax.data import SceneBatch, bucket_size, node_mask_from_positions
from gst_jax.errors import DataError
from gst_jax.predict import make_predict

# The id of a free slot; track ids are 0 or more (int32).
FREE = -1


@flax.struct.dataclass
class StreamState:
    """The tracks a stream holds, in C slots (any leading axes: robots).

    track_ids: (C,) int32, FREE for a free slot.
    positions: (C, T, 2) float32 metres, the last T = obs_len steps, oldest first; 0 where
      not detected.
    detected: (C, T) float32, 1 where the track was detected.
    dropped: () int32, new tracks refused so far for want of a free slot (the host grows
      the capacity and steps again when it rises).
    feed: the last P predictions of every slot, scored as the future is observed
      (`conformal.ScoreBufferState`), or None without regions.
    regions: the conformal state of the regions (`Regions`): one instance per horizon step
      (pooled), or per slot and horizon step; None without.
    """

    track_ids: jax.Array
    positions: jax.Array
    detected: jax.Array
    dropped: jax.Array
    feed: Any = None
    regions: Any = None

    @property
    def capacity(self) -> int:
        return self.track_ids.shape[-1]


class Frame(NamedTuple):
    """The people detected in one frame: ids (M,) int32 (FREE pads), positions (M, 2)."""

    ids: jax.Array
    positions: jax.Array


def init_state(capacity: int, obs_len: int, regions: "Regions | None" = None,
               pred_len: int = 0) -> StreamState:
    """An empty stream of `capacity` slots (with `regions`: of `pred_len` predicted steps)."""
    state = StreamState(track_ids=jnp.full((capacity,), FREE, jnp.int32),
                        positions=jnp.zeros((capacity, obs_len, 2), jnp.float32),
                        detected=jnp.zeros((capacity, obs_len), jnp.float32),
                        dropped=jnp.zeros((), jnp.int32))
    if regions is None:
        return state
    return state.replace(feed=conformal.score_buffer_init(capacity, pred_len, jnp.float32),
                         regions=regions.init(capacity, pred_len))


def observe(state: StreamState, frame: Frame) -> StreamState:
    """The state one step later: every slot's history moves back a step, the frame's people
    are written at the newest step (a known id into its slot, a new id into a free slot in
    the order of the frame), and tracks unseen for all T steps free their slots first."""
    ids = jnp.asarray(frame.ids, jnp.int32)
    positions = jnp.roll(state.positions, -1, axis=-2).at[..., -1, :].set(0.0)
    detected = jnp.roll(state.detected, -1, axis=-1).at[..., -1].set(0.0)
    track_ids = jnp.where(detected.any(axis=-1), state.track_ids, FREE)

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
    positions = positions.at[:, -1].set(jnp.where(written[:, None], newest, 0.0))
    detected = detected.at[:, -1].set(written.astype(jnp.float32))
    dropped = state.dropped + (new & ~taken.any(axis=0)).sum().astype(jnp.int32)
    return state.replace(track_ids=track_ids, positions=positions, detected=detected,
                         dropped=dropped)


def as_batch(state: StreamState) -> SceneBatch:
    """The state as a one-scene batch of the model's (T = obs_len observed steps)."""
    positions = jnp.swapaxes(state.positions, 0, 1)[None]                       # (1, T, C, 2)
    position_mask = jnp.swapaxes(state.detected, 0, 1)[None]                    # (1, T, C)
    return SceneBatch(positions=positions, position_mask=position_mask,
                      node_mask=node_mask_from_positions(position_mask),
                      scene_mask=jnp.ones(1), window_index=jnp.zeros(1, jnp.int32))


@dataclasses.dataclass(frozen=True)
class Regions:
    """Calibrated discs around every predicted step (`gst_jax.conformal`): each prediction is
    scored k steps later, at horizon k, by its distance to the position observed then, and an
    online method turns the scores into the next radii.

    method: "dtaci" (GenSafeNav's variant, consistent loss, drawn expert), "aci" (window of
    1000 scores), or None: score only, every radius infinite (split conformal is calibrated
    from those scores, `gst_jax.conformal.split_radius`). alpha: target miscoverage. pooled:
    one instance per horizon step, fed every track's score (default), or one per slot and
    horizon step, fed that track's alone (GenSafeNav's ROS 2 node; a new track starts from
    scratch). options: (name, value) pairs for the method's constructor, e.g.
    (("gamma", 0.002),) (`conformal.aci`, `conformal.dtaci`). The scored prediction is the
    mean of the K samples.
    """

    method: str | None = "dtaci"
    alpha: float = 0.1
    pooled: bool = True
    options: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self):
        if self.method not in ("dtaci", "aci", None):
            raise ValueError(f"method must be 'dtaci', 'aci' or None, got {self.method!r}")

    @property
    def online(self) -> conformal.OnlineConformal | None:
        if self.method is None:
            return None
        return getattr(conformal, self.method)(self.alpha, **dict(self.options))

    def init(self, capacity: int, horizon: int) -> Any:
        """Fresh states: (P,) pooled, (C, P) per track; DtACI's experts start at 0.1 m per
        horizon step."""
        if self.online is None:
            return None
        start = 0.1 * jnp.arange(1, horizon + 1, dtype=jnp.float32)              # (P,)
        if not self.pooled:
            start = jnp.broadcast_to(start, (capacity, horizon))
        if self.method == "dtaci":
            init = self.online.init
            for _ in range(start.ndim):
                init = jax.vmap(init)
            return init(start)
        return jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, start.shape + leaf.shape),
                            self.online.init(jnp.float32))

    def update(self, state: StreamState, key: jax.Array, new_slots: jax.Array,
               futures: jax.Array, predicted: jax.Array
               ) -> tuple[StreamState, jax.Array, conformal.DelayedScores]:
        """Score the predictions of 1..P steps ago against the positions observed now, update
        the radii, and keep this step's predictions (futures (K, P, C, 2), predicted (C,)).
        Returns the state, the radii issued with this step's predictions (C, P) and the
        delayed scores (scores, mask, issued: (C, P))."""
        feed = conformal.reset_slots(state.feed, new_slots)
        mean = jnp.moveaxis(futures.mean(axis=0), 1, 0)                           # (C, P, 2)
        feed, delayed = conformal.score_buffer_update(
            feed, mean, predicted > 0, state.positions[:, -1], state.detected[:, -1] > 0)
        regions, radii = self.advance(state.regions, key, new_slots, delayed)
        feed = conformal.record_issued(feed, radii)
        return state.replace(feed=feed, regions=regions), radii, delayed

    def advance(self, regions: Any, key: jax.Array, new_slots: jax.Array,
                delayed: conformal.DelayedScores) -> tuple[Any, jax.Array]:
        """The conformal state after the delayed scores (C, P) came back (per track, the
        `new_slots` (C,) start afresh first), and the radii (C, P) to issue now (infinite
        without a method)."""
        capacity, horizon = delayed.scores.shape
        if regions is None:
            return None, jnp.full((capacity, horizon), jnp.inf)
        if not self.pooled:                                     # a new track starts afresh
            fresh = self.init(capacity, horizon)
            regions = jax.tree.map(
                lambda new, old: jnp.where(new_slots.reshape((-1,) + (1,) * (old.ndim - 1)),
                                           new, old), fresh, regions)
        scores, mask, issued = delayed
        if self.pooled:                                         # per horizon: the tracks' batch
            scores, mask, issued = scores.T, mask.T, issued.T
        else:                                                   # per slot: a batch of one
            scores, mask, issued = scores[..., None], mask[..., None], issued[..., None]
        update = self.online.update
        for _ in range(regions.radius.ndim):
            update = jax.vmap(update)
        if self.method == "aci":
            regions, radii = update(regions, scores, mask, issued)
        else:
            regions, radii = update(regions, scores, mask,
                                    jax.random.uniform(key, regions.radius.shape))
        return regions, jnp.broadcast_to(radii, (capacity, horizon))


@dataclasses.dataclass(frozen=True)
class StreamModel:
    """What a stream predicts with.

    config: the model's; num_samples: K futures per track (1 with `mean`); mean: every
    predicted step the mean of the output head (GST (P)'s Gaussian; GST (D) is its mean
    anyway), the graph still sampled where the model selects edges; convention: "gst" (the
    model reads undetected steps as gst_jax's windows hold them) or "crowdnav" (CrowdNav++'s
    predictor: -999 and its displacement mask, `gst_jax.crowdnav.predict`; mean mode).
    """

    config: ModelConfig
    num_samples: int = 1
    mean: bool = True
    convention: str = "gst"

    def __post_init__(self):
        if self.convention not in ("gst", "crowdnav"):
            raise ValueError(f"convention must be 'gst' or 'crowdnav', got {self.convention!r}")
        if self.convention == "crowdnav" and (self.num_samples != 1 or not self.mean):
            raise ValueError("CrowdNav++'s predictor predicts the mean only (num_samples=1, "
                             "mean=True)")


def predict_slots(model: StreamModel, params, key: jax.Array, state: StreamState
                  ) -> tuple[jax.Array, jax.Array]:
    """Every slot's future from its history: (futures (K, P, C, 2), predicted (C,)), where
    predicted is 1 for the tracks detected at both of the last two steps (the others'
    futures are meaningless)."""
    config = model.config
    if model.convention == "crowdnav":
        traj = jnp.where(state.detected[..., None] > 0, state.positions, crowdnav.MISSING)
        output, predicted = crowdnav.predict(params, config, traj[None],
                                             state.detected[None, ..., None])
        return jnp.swapaxes(output[0, ..., :2], 0, 1)[None], predicted[0, :, 0]
    prediction = make_predict(config, model.num_samples, with_graph=False, mean=model.mean)(
        params, key, as_batch(state))
    return prediction.positions[:, 0], prediction.predicted_mask[0]


def make_step(model: StreamModel, regions: Regions | None = None) -> Callable:
    """The pure `step(params, state, frame, key) -> (state, futures, predicted, radii,
    delayed)`: observe the frame, predict every slot (`predict_slots`), and with `regions`
    score the earlier predictions and issue this step's radii (C, P) (`Regions.update`;
    without, radii and delayed are None). jit it, vmap it over robots."""
    def step(params, state: StreamState, frame: Frame, key: jax.Array):
        before = state.track_ids
        state = observe(state, frame)
        predict_key, regions_key = jax.random.split(key)
        futures, predicted = predict_slots(model, params, predict_key, state)
        if regions is None:
            return state, futures, predicted, None, None
        new_slots = (state.track_ids != before) & (state.track_ids != FREE)
        state, radii, delayed = regions.update(state, regions_key, new_slots, futures,
                                               predicted)
        return state, futures, predicted, radii, delayed
    return step


@functools.lru_cache(maxsize=16)
def _jitted_step(model: StreamModel, regions: Regions | None) -> Callable:
    """`make_step` jitted once per (model, regions): streams of one model, one after another
    (a recorded scene's files), share its compiled programs."""
    return jax.jit(make_step(model, regions))


class StreamOutput(NamedTuple):
    """One frame's predictions, for the tracks predicted now (detected at both of the last
    two steps): ids (L,), futures (L, P, 2) in mean mode or (L, K, P, 2), and with regions
    the radii of their discs (L, P) (metres, around each predicted step; None without).
    delayed: the scores this frame's observations gave the earlier predictions, with the radii
    issued with them (`conformal.DelayedScores`, (C, P) over the slots), for measuring
    coverage; None without regions."""

    ids: np.ndarray
    futures: np.ndarray
    radii: np.ndarray | None = None
    delayed: conformal.DelayedScores | None = None


class Stream:
    """A stream over a tracker's output (numpy in and out): `step(ids, positions)` once per
    model step (`config.step_s` apart), the people detected then; ids are the tracker's,
    any non-negative integers.

    regions: conformal discs around the predictions (`Regions`), or None.
    robot: `step` also takes the robot's position, which joins the graph as one more agent
    (the people's predictions may react to it); it is never predicted.
    """

    # The robot's id among the tracks: no tracker's.
    ROBOT = np.iinfo(np.int32).max

    def __init__(self, run, *, num_samples: int = 1, mean: bool = True, capacity: int = 8,
                 seed: int = 0, convention: str = "gst", regions: Regions | None = None,
                 robot: bool = False):
        self.model = StreamModel(run.model_config, num_samples, mean, convention)
        self.params = run.params
        self.regions, self.robot = regions, robot
        self.key = jax.random.key(seed)
        self.frames = 0
        config = run.model_config
        self.state = init_state(bucket_size(capacity), config.obs_len, regions, config.pred_len)
        self._step = _jitted_step(self.model, regions)

    def step(self, ids, positions, robot_xy=None) -> StreamOutput:
        ids, positions = _checked_frame(ids, positions)
        if self.robot:
            if robot_xy is None:
                raise DataError("this stream has the robot as an agent: give robot_xy")
            ids = np.append(ids, self.ROBOT).astype(np.int32)
            positions = np.vstack([positions, np.reshape(robot_xy, (1, 2))])
        if len(ids) > self.state.capacity:
            self.state = self._grown(bucket_size(len(ids)))
        key = jax.random.fold_in(self.key, self.frames)
        while True:
            # Frames padded to the capacity: one compiled step per capacity.
            width = self.state.capacity
            frame = Frame(np.pad(ids, (0, width - len(ids)), constant_values=FREE),
                          np.pad(positions, [(0, width - len(ids)), (0, 0)]).astype(np.float32))
            state, futures, predicted, radii, delayed = self._step(self.params, self.state,
                                                                   frame, key)
            if int(state.dropped) == int(self.state.dropped):
                break
            self.state = self._grown(bucket_size(self.state.capacity + 1))
        self.state, self.frames = state, self.frames + 1
        track_ids = np.asarray(state.track_ids)
        keep = (np.asarray(predicted) > 0) & (track_ids != FREE) & (track_ids != self.ROBOT)
        futures = np.moveaxis(np.asarray(futures)[:, :, keep], 2, 0)            # (L, K, P, 2)
        return StreamOutput(track_ids[keep], futures[:, 0] if self.model.mean else futures,
                            None if radii is None else np.asarray(radii)[keep],
                            None if delayed is None else jax.tree.map(np.asarray, delayed))

    def _grown(self, capacity: int) -> StreamState:
        """The same tracks in `capacity` slots (the new ones free and, per track, with fresh
        regions)."""
        state, extra = self.state, capacity - self.state.capacity

        def pad(array, axis=0, value=0):
            widths = [(0, 0)] * array.ndim
            widths[axis] = (0, extra)
            return jnp.pad(array, widths, constant_values=value)

        grown = state.replace(track_ids=pad(state.track_ids, value=FREE),
                              positions=pad(state.positions), detected=pad(state.detected))
        if self.regions is None:
            return grown
        feed = state.feed._replace(predicted=pad(state.feed.predicted, 1),
                                   valid=pad(state.feed.valid, 1),
                                   issued=pad(state.feed.issued, 1))
        regions = state.regions
        if regions is not None and not self.regions.pooled:
            fresh = self.regions.init(extra, feed.predicted.shape[0])
            regions = jax.tree.map(lambda old, new: jnp.concatenate([old, new]), regions, fresh)
        return grown.replace(feed=feed, regions=regions)


def _checked_frame(ids, positions) -> tuple[np.ndarray, np.ndarray]:
    """A frame's ids (M,) and positions (M, 2), or a one-line refusal."""
    ids = np.asarray(ids)
    positions = np.asarray(positions, np.float64).reshape(-1, 2) if np.size(positions) else (
        np.zeros((0, 2)))
    if ids.ndim != 1 or len(ids) != len(positions):
        raise DataError(f"a frame needs ids (M,) and positions (M, 2); got {ids.shape} and "
                        f"{np.shape(positions)}")
    if len(ids) and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0
                     or ids.max() >= Stream.ROBOT):
        raise DataError(f"track ids must be integers from 0 to {Stream.ROBOT - 1}, got "
                        f"{ids[:5].tolist()}...")
    if len(np.unique(ids)) != len(ids):
        values, counts = np.unique(ids, return_counts=True)
        raise DataError(f"track id {values[counts > 1][0]} appears twice in one frame")
    if not np.isfinite(positions).all():
        index = int(np.argwhere(~np.isfinite(positions))[0, 0])
        raise DataError(f"track {ids[index]}'s position is {positions[index].tolist()}: not "
                        "finite (leave an undetected person out of the frame)")
    return ids.astype(np.int32), positions
