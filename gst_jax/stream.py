"""Prediction over a tracker's output, one frame at a time: what a robot runs.

    stream = Stream(load_model("pretrained:crowdnav_sim"))
    out = stream.step(track_ids, positions)             # the people detected now
    out.ids, out.futures                                 # (L,), (L, P, 2) or (L, K, P, 2)

Each track keeps its last `obs_len` positions with a detection mask in a slot of a fixed
capacity, as a window's pedestrians do: a track that appears is partially detected (GST's
point: it is predicted from the steps it was seen), one unseen for `obs_len` steps is dropped
and its slot reused. Capacity follows the crowd by the buckets of `gst_jax.data.bucket_size`,
so that a crowd that changes size meets few compiled programs: it grows at once, and shrinks
(the tracks compacted) once they have fitted a smaller bucket for `SHRINK_AFTER` frames in a
row. `Stream.warm_up` compiles them all before the robot moves, and `compilation_cache=DIR`
keeps them on disk for the next process. A frame the model cannot predict in time (a capacity
whose program still compiles, in the background; a step past its deadline; a step that failed)
gets constant velocity, computed on the host with the tracks kept whole
(`gst_jax.stream_fallback`, `StreamOutput.fallback`), and the loop goes on. Compiles, capacity
changes, overruns and fallbacks are logged (logger "gst_jax.stream"); nothing is printed.

A tracker's id names one person until the tracker says otherwise: `Stream.forget(ids)` or
`step(..., lost=ids)` ends those tracks (an id the tracker recycles then starts a new one),
and an id that reappears where its track could not have gone (`Gate`: beyond `max_speed`, or
farther from where its recent velocity would have carried it than `max_acceleration` allows)
starts a new track too (`StreamOutput.restarted`), so that two people are never glued into
one history and the old person's pending predictions are never scored against the newcomer.

A tracker at another rate than the model's (5 Hz, 10 Hz, jittered, frames dropped) gives each
frame's `time`: the stream resamples its tracks to the model's steps (`gst_jax.stream_time`:
each track interpolated to each tick of a fixed grid from its detections on both sides, at
most one tick late), and a gap in the frames runs the model once, not once per missing step.

Underneath, everything is a pure function of arrays, so that it jits, vmaps over robots
(environments, as CrowdNav++ trains) and runs inside a planner's program: the core,
`gst_jax.stream_core`, whose every name this module re-exports (import them from here):

    state = init_state(capacity, obs_len)               # StreamState
    state = observe(state, frame, gate)                  # Frame: ids (M,), positions (M, 2)
    futures, predicted = predict_slots(model, params, key, state)

`Stream`, this module, is the host around them: numpy in and out, ids in any order, capacity
growth, frame times, forgotten and restarted tracks, compiling ahead (`warm_up`). The model
is any gst_jax model (the paper's, `crowdnav_sim`, ...) or CrowdNav++'s (`crowdnav.predict`,
with its own input conventions). Conformal discs around the predictions are
`gst_jax.conformal.Regions` (importable from here too), issued by `update_regions` from the
stream's score buffer.

Constant velocity with the same discs, the baseline a model has to beat, needs no model file:

    stream = Stream(ConstantVelocity(obs_len=8, pred_len=12), step_s=0.4, regions=...)

A restarted robot resumes with its tracks and discs warm: `stream.save(path)` writes them to
one file (atomically; `gst_jax.stream_file`), `Stream(run, ...).load(path)` reads them back
into a stream built as that one was, which then steps as the saved one would have, bit for bit.
"""

from __future__ import annotations

import functools
import logging
import math
import numbers
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from time import perf_counter
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from gst_jax import conformal, stream_fallback, stream_file
from gst_jax.adaptation import Adaptation
from gst_jax.compiles import use_persistent_cache
from gst_jax.config import TimeGrid, check as check_config, rules
from gst_jax.conformal import Regions
from gst_jax.data import bucket_size
from gst_jax.data.batching import LARGEST_COORDINATE
from gst_jax.errors import DataError
from gst_jax.model import Params
from gst_jax.predict import check_compiler_room, compile_checked
from gst_jax.predictors import ConstantVelocity, Predictor, Standing
from gst_jax.stream_core import (
    FREE,
    Frame,
    Gate,
    StreamModel,
    StreamState,
    adapt,
    as_batch,
    init_state,
    make_step,
    observe,
    predict_slots,
    update_regions,
)
from gst_jax.stream_time import Clock

__all__ = [
    # the host: numpy in and out, ids, capacity growth, times, compiling ahead
    "Stream", "StreamOutput", "MAX_SPEED", "MAX_ACCELERATION", "JUMP_TOLERANCE", "NON_FINITE",
    "SHRINK_AFTER", "DEADLINE_S", "FALLBACKS",
    # re-exported: the pure core (gst_jax.stream_core) and the regions (gst_jax.conformal)
    "FREE", "Frame", "Gate", "StreamModel", "StreamState", "adapt", "as_batch", "init_state",
    "make_step", "observe", "predict_slots", "update_regions", "Regions",
]

logger = logging.getLogger("gst_jax.stream")

# `Stream`'s default gate (`Gate`), when a known id's detection is another person's: nobody
# moves faster than MAX_SPEED (m/s: a cyclist; a jogger runs 3, a walker 1.4), and a track seen
# at least twice moves on at its last velocity give or take JUMP_TOLERANCE (m: a tracker's
# noise, a simulated human turning back at its goal) + MAX_ACCELERATION (m/s^2) x the elapsed
# time^2 / 2. It restarts none of ETH/UCY's or the simulated crowd's annotated tracks, a step
# or three later (the rule before, 2.5 m/s alone, restarted 46 % of ETH's steps), and a walker
# at 1 m/s reappearing 3 m from where it would be is another person up to 0.75 s later (1.13 m
# allowed after 0.25 s, 2.13 m after 0.75 s): experiments/identity_gate.py, docs/robot.md.
MAX_SPEED = 8.0
MAX_ACCELERATION = 4.0
JUMP_TOLERANCE = 1.0
# What `Stream(non_finite=...)` does with a detection whose position is NaN or infinite.
NON_FINITE = ("raise", "undetected")
# A stream shrinks once the tracks it holds have fitted a smaller bucket of
# `gst_jax.data.bucket_size` for this many frames in a row (5 s at 0.25 s a step): a crowd that
# hovers at a bucket's edge keeps its capacity, and one that has gone gives back what its larger
# program costs a step (issue 92's report: crowd_d at 128 slots, 1.9 s a step with 40 people
# where 48 slots took 76 ms).
SHRINK_AFTER = 20
# `Stream`'s deadline_s where none is given: "step", the model's period (a robot's loop). The
# test suite sets None (tests/conftest.py): no test's frame may depend on the machine's load.
DEADLINE_S: float | str | None = "step"
# Why constant velocity, not the model, predicted a frame (`StreamOutput.fallback`): the
# program of the capacity the crowd needs compiles in the background; the model's step took
# longer than the deadline (or an earlier one that did still runs); the model's step failed.
FALLBACKS = ("compiling", "overrun", "error")


@functools.lru_cache(maxsize=16)
def _jitted_step(model: Predictor, regions: Regions | None, gate: Gate | None,
                 adaptation: Adaptation | None = None, step_s: float | None = None
                 ) -> Callable:
    """`make_step` jitted once per (model, regions, gate, adaptation, step_s), with the
    key of the step folded in: streams of one model, one after another (a recorded scene's
    files), share its compiled programs. Its `idle` empty steps (after a gap in the frames)
    come before the step, which folds in the index it reaches."""
    step = make_step(model, regions, gate=gate, step_s=step_s, adaptation=adaptation)

    def host_step(params: Params, state: StreamState, frame: Frame, key: jax.Array,
                  index: jax.Array, idle: jax.Array):
        return step(params, state, frame, jax.random.fold_in(key, index + idle), idle)
    return jax.jit(host_step)


class StreamOutput(NamedTuple):
    """One frame's predictions, for the tracks predicted now (detected at both of the last
    two steps): ids (L,), futures (L, P, 2) in mean mode or (L, K, P, 2), and with regions
    the radii of their discs (L, P) (metres, around each predicted step; None without).
    delayed: the scores this frame's observations gave the earlier predictions, with the radii
    issued with them (`conformal.DelayedScores`, (C, P) over the slots), for measuring
    coverage; None without regions. restarted: the ids whose track restarted at this frame,
    seen where their track could not have gone (`Gate`: another person under a recycled id,
    or a tracker's switch).

    With frame times (`Stream.step(..., time=)`): time, the time (s) of the model's step the
    predictions start from (`futures[..., k, :]` is at time + (k + 1) step_s); ticks, the
    model steps this frame reached: 0 where it reached none (the last tick's ids, futures and
    radii again, nothing scored: `repeated`), more than 1 after a gap (delayed: the last
    one's scores). Without: time None, ticks 1.

    fallback: None where the model predicted this frame; else why constant velocity did
    (`FALLBACKS`: "compiling", "overrun", "error"; `Stream`'s deadline_s), each track's last
    displacement repeated, with the radii in force and nothing scored (`delayed` all masked).
    """

    ids: np.ndarray
    futures: np.ndarray
    radii: np.ndarray | None = None
    delayed: conformal.DelayedScores | None = None
    restarted: np.ndarray = np.zeros(0, np.int32)
    time: float | None = None
    ticks: int = 1
    fallback: str | None = None

    @property
    def repeated(self) -> bool:
        """Whether this frame reached no model step: the last step's predictions again."""
        return self.ticks == 0


class Stream:
    """A stream over a tracker's output (numpy in and out): `step(ids, positions)`, the
    people detected in a frame; ids are the tracker's, any non-negative integers. Without
    `time`, each frame is one model step (`config.step_s` after the last): a tracker at another
    rate, or whose frames jitter or drop, must give each frame's `time` (`step`), and its
    tracks are resampled to the model's steps.

    run: a loaded model (`gst_jax.runs.load_model`), or a predictor that needs no model file,
    `ConstantVelocity(obs_len, pred_len)` or `Standing(...)` (`gst_jax.predictors`), with
    `step_s`, the seconds between its steps (a model has its own); num_samples, mean and
    convention are a model's (`gst_jax.predictors.GST`).
    regions: conformal discs around the predictions (`gst_jax.conformal.Regions`), or None.
    adaptation: an online correction of the predictions from their delayed scores
    (`gst_jax.adaptation`, e.g. `SpeedScale()`), applied before the discs, or None.
    robot: `step` also takes the robot's position, which joins the graph as one more agent
    (the people's predictions may react to it); it is never predicted.
    max_speed, max_acceleration, jump_tolerance: when a known id's detection is another
    person's (`Gate`; defaults MAX_SPEED 8 m/s, MAX_ACCELERATION 4 m/s^2, JUMP_TOLERANCE 1 m).
    An id seen farther from its last position than max_speed allows over the time since, or
    (seen twice or more) farther from where its last velocity would have carried it than
    jump_tolerance + max_acceleration x time^2 / 2, starts a new track (its old history and
    pending predictions are dropped; `StreamOutput.restarted`). max_acceleration None: the
    speed rule alone (before issue 92: max_speed=2.5, max_acceleration=None); max_speed None:
    never (recorded annotations, whose ids are ground truth).
    non_finite: "raise" (default) refuses a frame with a NaN or infinite position in one line
    (`DataError`); "undetected" reads such a detection as that person not detected at this
    step, the others' detections kept.
    compilation_cache: a folder where JAX keeps every compiled program of this process
    (`gst_jax.compiles.use_persistent_cache`): a restarted robot loads its programs from it
    instead of compiling them again. None: the process's own setting.
    deadline_s: how long a frame waits for the model ("step": the model's period, `step_s`;
    by default DEADLINE_S, "step"). A crowd that needs a capacity this stream has not compiled
    gets its program compiled in the background (`warm_up` compiles ahead), and a model's step
    not done in time runs on unused: meanwhile constant velocity predicts, on the host, the
    tracks kept whole for the model to take over (`StreamOutput.fallback`, as where the
    model's step fails). None: every frame waits for the model, compiling included (a
    recording replayed or measured). Each model step runs in a thread of the stream's with a
    deadline.
    shrink_after: frames in a row whose tracks fit a smaller bucket before the capacity
    shrinks to it, the tracks compacted (default SHRINK_AFTER, 20); None: never.
    Compiles (with their seconds), capacity changes, overruns and constant velocity's frames
    are logged (`logging`, logger "gst_jax.stream"); nothing is printed.
    """

    # The robot's id among the tracks: no tracker's.
    ROBOT = np.iinfo(np.int32).max

    def __init__(self, run, *, num_samples: int = 1, mean: bool = True, capacity: int = 8,
                 seed: int = 0, convention: str = "gst", regions: Regions | None = None,
                 robot: bool = False, max_speed: float | None = MAX_SPEED,
                 non_finite: str = "raise", compilation_cache: str | None = None,
                 adaptation: Adaptation | None = None,
                 max_acceleration: float | None = MAX_ACCELERATION,
                 jump_tolerance: float = JUMP_TOLERANCE, step_s: float | None = None,
                 deadline_s: float | str | None = "default",
                 shrink_after: int | None = SHRINK_AFTER):
        if deadline_s == "default":
            deadline_s = DEADLINE_S
        if non_finite not in NON_FINITE:
            raise DataError(f"Stream: non_finite must be one of {NON_FINITE}, got "
                            f"{non_finite!r}")
        gate = [_gate_limit("max_speed", max_speed, "a positive number of m/s (or None)"),
                _gate_limit("max_acceleration", max_acceleration,
                            "a positive number of m/s^2 (or None)"),
                _gate_limit("jump_tolerance", jump_tolerance, "a number of metres, 0 or more",
                            0.0)]
        if deadline_s != "step" and deadline_s is not None and not (
                isinstance(deadline_s, numbers.Real) and 0 < deadline_s < math.inf):
            raise DataError(f"Stream: deadline_s must be a positive number of seconds, \"step\" "
                            f"(the model's step_s) or None (wait), got {deadline_s!r}")
        if shrink_after is not None and not (isinstance(shrink_after, numbers.Integral)
                                             and shrink_after >= 1):
            raise DataError(f"Stream: shrink_after must be a number of frames, 1 or more (or "
                            f"None: never shrink), got {shrink_after!r}")
        if compilation_cache is not None:
            use_persistent_cache(compilation_cache)
        self.model: Predictor
        if isinstance(run, (ConstantVelocity, Standing)):
            if (num_samples, mean, convention) != (1, True, "gst"):
                raise DataError(f"Stream: num_samples, mean and convention are a model's; "
                                f"{type(run).__name__} predicts one future per track")
            self.model, self.params, self.mean = run, None, True
            self.grid = _predictor_grid(run, step_s)
        else:
            if step_s is not None:
                raise DataError("Stream: a model steps at its own step_s (its config's); "
                                "give step_s only with a predictor without a model")
            self.model = StreamModel(run.model_config, num_samples, mean, convention)
            self.params, self.mean, self.grid = run.params, mean, run.model_config.grid
        self.regions, self.robot, self.adaptation = regions, robot, adaptation
        self.max_speed = None if max_speed is None else float(max_speed)
        self.gate = None if gate[0] is None else Gate(gate[0], gate[1], gate[2] or 0.0)
        self.non_finite = non_finite
        self.key = jax.random.key(seed)
        self.frames = 0              # model steps so far (the key of step t folds in t)
        self.restarts = 0            # tracks restarted so far (`StreamOutput.restarted`)
        self._lost: set[int] = set()
        config = self.grid
        # Frame times resampled to the model's steps (`step(..., time=)`); with the state and
        # the counters above, all a stream holds between frames.
        self._clock = Clock(config.step_s)
        self.state = _initial_state(bucket_size(capacity), config.obs_len, regions,
                                    config.pred_len, adaptation)
        # Per track, the regions of one fresh slot, to give the slots a growing stream adds.
        self._fresh_regions = None if regions is None or regions.pooled else _host_tree(
            regions.init(1, config.pred_len))
        self._step = _jitted_step(self.model, regions, self.gate, adaptation,
                                  config.step_s)
        self.deadline_s: float | None = (config.step_s if deadline_s == "step" else
                                         None if deadline_s is None else float(deadline_s))
        self.shrink_after = shrink_after
        # Capacities: the smallest it shrinks to; and its programs, with their compiles' seconds.
        self._floor = self.state.capacity
        self._compiled: dict[int, float] = {}
        self._compiling: tuple[int, Future] | None = None   # (capacity, its background compile)
        self._failed: set[int] = set()                       # capacities that failed to compile
        # Frames in a row whose tracks fitted a smaller bucket, and the most tracks over them.
        self._small_frames, self._small_peak = 0, 0
        self._worker: ThreadPoolExecutor | None = None      # where model steps run, timed
        self._running: Future | None = None     # a step past its deadline, still running
        self.fallbacks = 0           # frames predicted by constant velocity (`FALLBACKS`)
        self.overruns = 0            # model steps that took longer than the model's period
        self._fallback: str | None = None        # why the last step's predictions are CV's
        self._fallback_since, self._error = 0, ""

    def step(self, ids, positions, robot_xy=None, *, time: float | None = None,
             lost=None) -> StreamOutput:
        """The predictions after this frame: ids (M,) of the people detected now, positions
        (M, 2) in metres. lost: ids the tracker reports lost at this frame, ended before its
        detections are matched (`forget`).

        time: the frame's time in seconds (any origin). The model steps on a grid from the first
        frame's time, `step_s` apart; this frame reaches every step of it since the last frame
        up to its own time (`StreamOutput.time`, `.ticks`), each track interpolated linearly
        there from its detections on both sides, at most two model steps apart
        (`gst_jax.stream_time`): any rate, jitter or dropped frames, none refused; a frame at
        or before the last one's time is (`DataError`). A track missing from a frame is
        filled in once seen again within two steps; steps where nobody was seen (a gap) run
        at once, without the model. Without time, a frame is one model step after the last."""
        ids, positions = _checked_frame(ids, positions, self.non_finite)
        if self.robot:
            if robot_xy is None:
                raise DataError("this stream has the robot as an agent: give robot_xy")
            robot_xy = np.asarray(robot_xy, np.float64)
            if robot_xy.shape not in ((2,), (1, 2)) or not np.isfinite(robot_xy).all() or (
                    np.abs(robot_xy).max() > LARGEST_COORDINATE):
                raise DataError(f"robot_xy must be one finite position (2,) within "
                                f"{LARGEST_COORDINATE:.0e} m, got {robot_xy.tolist()}")
            ids = np.append(ids, self.ROBOT).astype(np.int32)
            positions = np.vstack([positions, robot_xy.reshape(1, 2)])
        clock = self._clock
        if time is None and clock.last_time is not None:       # a timed stream
            time = clock.last_time + clock.step_s
        if time is not None:
            time = clock.checked_time(time)
        if lost is not None:
            self.forget(lost)
        if time is None:
            return self._output([self._advance(ids, positions)])
        first = clock.ticks
        reached = clock.frame(time, ids, positions, self.gate)
        filled_ids, filled_ticks, filled_xy = reached.fills
        self._fill(filled_ids, filled_ticks, filled_xy, first)
        if len(reached.restarted):     # their old tracks end at the next step, as forgotten
            self._lost.update(reached.restarted.tolist())
        steps, idle = [], 0
        for n, tick in enumerate(reached.ticks):
            if len(tick.ids) == 0 and n < len(reached.ticks) - 1:
                idle += 1
                continue
            # Beyond obs_len + pred_len empty steps nothing is left to predict or to score.
            skipped = max(0, idle - self.grid.obs_len - self.grid.pred_len)
            self.frames += skipped
            steps.append(self._advance(tick.ids, tick.positions, idle - skipped))
            idle = 0
        if not steps:
            return self._repeated(reached.restarted, time)
        return self._output(steps, reached.restarted, reached.ticks[-1].time,
                            len(reached.ticks))

    def _output(self, steps: list[tuple], restarted: np.ndarray | None = None,
                time: float | None = None, ticks: int = 1) -> StreamOutput:
        """The output of the last of a frame's model steps (`_advance`'s), with the tracks
        restarted at any of them or before (`restarted`, the raw detections' restarts)."""
        restarted = np.zeros(0, np.int32) if restarted is None else restarted
        for state, *_ in steps:
            track_ids = np.asarray(state.track_ids)
            restarted = np.append(restarted, track_ids[np.asarray(state.restarted)])
        restarted = self._restarted(restarted, time)
        state, futures, predicted, radii, delayed = steps[-1]
        track_ids = np.asarray(state.track_ids)
        keep = (predicted > 0) & (track_ids != FREE) & (track_ids != self.ROBOT)
        futures = np.moveaxis(futures[:, :, keep], 2, 0)                        # (L, K, P, 2)
        output = StreamOutput(track_ids[keep], futures[:, 0] if self.mean else futures,
                              None if radii is None else radii[keep], delayed, restarted,
                              time, ticks, self._fallback)
        self._clock.last_output = {"ids": output.ids, "futures": output.futures,
                                   "radii": output.radii}
        return output

    def _repeated(self, restarted: np.ndarray, time: float) -> StreamOutput:
        """A frame that reached no model step: the last step's predictions again (ticks 0),
        nothing scored."""
        clock = self._clock
        last = clock.last_output
        assert last is not None, "the first frame reaches its step"
        delayed = None
        if self.regions is not None:
            shape = (self.state.capacity, self.grid.pred_len)
            nothing: list[Any] = [np.zeros(shape, np.float32), np.zeros(shape, bool),
                                  np.zeros(shape, np.float32)]
            delayed = conformal.DelayedScores(*nothing)
        return StreamOutput(last["ids"], last["futures"], last["radii"], delayed,
                            self._restarted(restarted, time), clock.tick_time(clock.ticks - 1), 0,
                            self._fallback)

    def _restarted(self, ids: np.ndarray, time: float | None) -> np.ndarray:
        """The tracks restarted at a frame (sorted, the robot left out), counted and logged."""
        ids = np.unique(ids[ids != self.ROBOT]).astype(np.int32)
        if len(ids):
            self.restarts += len(ids)
            logger.info("tracks %s restarted%s: each seen where its track could not have gone "
                        "(another person under a recycled id, or a tracker's switch)",
                        ids.tolist(), "" if time is None else f" at {time:.3f} s")
        return ids

    def _fill(self, ids: np.ndarray, ticks: np.ndarray, positions: np.ndarray, first: int
              ) -> None:
        """Write the detections of tracks missed at earlier steps (ticks (F,) of the clock,
        `first` the next) into their histories, where the step is still held."""
        if not len(ids):
            return
        track_ids = np.asarray(self.state.track_ids)
        history = np.array(self.state.positions)
        detected = np.array(self.state.detected)
        columns = detected.shape[-1] - first + ticks
        for track, column, xy in zip(ids, columns, positions):
            slot = np.flatnonzero(track_ids == track)
            if len(slot) and column >= 0:
                history[slot[0], column], detected[slot[0], column] = xy, 1.0
        self.state = self.state.replace(positions=history, detected=detected)

    def forget(self, ids) -> None:
        """End the tracks of these ids (a tracker's lost tracks) at the next step, before that
        frame's detections: an id among them seen again starts a new track, and the old
        track's pending predictions are never scored. The way to end a track: give the ids
        your tracker reports lost here, or with their frame (`step(..., lost=)`)."""
        ids = np.asarray(ids).reshape(-1)
        if len(ids) and not np.issubdtype(ids.dtype, np.integer):
            raise DataError(f"forget: track ids must be integers, got {ids[:5].tolist()}")
        self._lost.update(int(i) for i in ids)
        self._clock.forget(ids)

    def warm_up(self, max_people: int) -> tuple[int, ...]:
        """Compile the step of every capacity this stream can grow to while it holds at most
        `max_people` tracks (those in view and those unseen for fewer than obs_len steps), so
        that no step compiles later; returns the capacities. Each is one program: with
        CrowdNav++'s predictor and DtACI regions, 35 s for the six up to 64 on a loaded 2-core
        CPU, 5.8 s from a warm `compilation_cache` (the programs read, each step traced)
        (docs/robot.md). The stream's own state is left as it was."""
        if not (isinstance(max_people, numbers.Integral) and max_people >= 0):
            raise DataError(f"warm_up: max_people must be a whole number, got {max_people!r}")
        largest = bucket_size(max_people + (1 if self.robot else 0))
        capacities = [self.state.capacity]
        while capacities[-1] < largest:
            capacities.append(bucket_size(capacities[-1] + 1))
        state = self.state
        try:
            for capacity in capacities:         # the step on the tracks as they are, unkept
                self.state = state
                self.state = self._resized(capacity)
                self._run(np.zeros(0, np.int32), np.zeros((0, 2)), np.zeros(0, np.int32))
        finally:
            self.state = state
        return tuple(capacities)

    def _advance(self, ids: np.ndarray, positions: np.ndarray, idle: int = 0) -> tuple:
        """One model step over a checked frame, after `idle` steps where nobody was detected
        (run without the model), in a state of the capacity its tracks need (`_fit`): the state
        moves on; returns it and the step's outputs as numpy arrays. Where the model cannot
        give this frame's predictions in time, constant velocity gives them, on the host
        (`_constant_velocity`; why: `self._fallback`, `StreamOutput.fallback`)."""
        lost = np.zeros(0, np.int32)
        if self._lost:
            held = set(np.asarray(self.state.track_ids).tolist())
            lost = np.array(sorted(self._lost & held), np.int32)
            self._lost.clear()
        self._fit(ids, lost, idle)
        reason, outcome = self._model_step(ids, positions, lost, idle)
        if outcome is None:
            outcome = self._constant_velocity(ids, positions, lost, idle)
        self._note_fallback(reason)
        self.state, self.frames = outcome[0], self.frames + 1 + idle
        return outcome

    def _model_step(self, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray,
                    idle: int) -> tuple[str | None, tuple | None]:
        """(None, the model's step) or (why not, None): "compiling" (this capacity's program
        compiles in the background), "overrun" (this step, or an earlier one still running,
        took longer than `deadline_s`), "error" (it raised; logged)."""
        capacity = self.state.capacity
        if capacity not in self._compiled and not self._compiles_inline():
            return ("error" if capacity in self._failed else "compiling"), None
        if self._running is not None:
            if not self._running.done():
                return "overrun", None
            self._running = None             # its outputs came too late to be anyone's
        try:
            outcome = self._run_in_time(ids, positions, lost, idle)
        except DataError:
            raise                            # a refusal (memory), with its fix: the user's
        except Exception as error:           # any other failure: the robot goes on, on CV
            self._error = (f"the model's step failed: {type(error).__name__}: "
                           f"{str(error).splitlines()[0][:300]}")
            logger.debug("the model's step at frame %d failed", self.frames, exc_info=True)
            return "error", None
        return ("overrun", None) if outcome is None else (None, outcome)

    def _compiles_inline(self) -> bool:
        """Whether a program this stream lacks is compiled at its step, the loop waiting:
        without a deadline, and for its first program (before the loop runs)."""
        return self.deadline_s is None or not self._compiled

    def _args(self, state: StreamState, ids: np.ndarray, positions: np.ndarray,
              lost: np.ndarray, idle: int = 0) -> tuple:
        """The jitted step's arguments: the frame padded to the state's capacity."""
        width = state.capacity
        frame = Frame(np.pad(ids, (0, width - len(ids)), constant_values=FREE),
                      np.pad(positions, [(0, width - len(ids)), (0, 0)]).astype(np.float32),
                      np.pad(lost, (0, width - len(lost)), constant_values=FREE))
        return (self.params, state, frame, self.key, np.int32(self.frames), np.int32(idle))

    def _run(self, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray, idle: int = 0
             ) -> tuple:
        """The jitted step on the state as it is, frames padded to the capacity (one compiled
        step per capacity, compiled here if this stream has not yet): the state (on the
        device) and the outputs as numpy."""
        args = self._args(self.state, ids, positions, lost, idle)
        self._compile_inline(args)
        return _call(self._step, args)

    def _run_in_time(self, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray,
                     idle: int) -> tuple | None:
        """`_run`, timed: with a deadline, in this stream's worker thread, None where it is not
        done by then (it runs on, `self._running`, its outputs never used). A step slower than
        the model's period is an overrun: counted (`overruns`) and logged."""
        args = self._args(self.state, ids, positions, lost, idle)
        self._compile_inline(args)
        started = perf_counter()
        if self.deadline_s is None:
            outcome = _call(self._step, args)
        else:
            if self._worker is None:
                self._worker = ThreadPoolExecutor(1, thread_name_prefix="gst_jax.stream.step")
                weakref.finalize(self, self._worker.shutdown, wait=False)
            job = self._worker.submit(_call, self._step, args)
            try:
                outcome = job.result(timeout=self.deadline_s)
            except TimeoutError:             # logged as constant velocity's start
                self._running, outcome = job, None
        seconds = perf_counter() - started
        if seconds > self.grid.step_s:
            self.overruns += 1
            if outcome is not None:          # waited for: deadline_s None, or beyond step_s
                log = logger.warning if self.overruns == 1 else logger.debug
                log("frame %d: the model's step over %d slots took %.3f s, longer than its "
                    "period (%g s; overrun %d)", self.frames, self.state.capacity, seconds,
                    self.grid.step_s, self.overruns)
        return outcome

    def _compile_inline(self, args: tuple) -> None:
        """Compile the step for `args`, the loop waiting, unless this stream has it."""
        capacity = args[1].capacity
        if capacity not in self._compiled:
            self._compiled[capacity] = _compile(self._step, args, self._checked_config(),
                                                self.grid.step_s, "")

    def _checked_config(self):
        """The model config whose memory `compile_checked` weighs before a capacity's first
        step (issue 78: a gst_jax model's; None for CrowdNav++'s and predictors without one)."""
        if isinstance(self.model, StreamModel) and self.model.convention == "gst":
            return self.model.config
        return None

    def _fit(self, ids: np.ndarray, lost: np.ndarray, idle: int) -> None:
        """Give the state the capacity this frame's tracks need (the module docstring): grown
        to the smallest capacity compiled that holds them, else to their bucket (its program
        compiled in the background, constant velocity meanwhile, where there is a deadline);
        shrunk, the tracks compacted, once they have fitted a smaller bucket for
        `shrink_after` frames in a row and its program is compiled. A capacity holds the tracks
        both before this frame's step and after it (the tracks that end, end inside it)."""
        self._collect_compile()
        held = self._held_after(ids, lost, idle)
        needed = max(held, int((np.asarray(self.state.track_ids) != FREE).sum()))
        capacity = self.state.capacity
        holding = sorted(c for c in self._compiled if c >= needed)
        if held > capacity:
            target = holding[0] if holding else bucket_size(held)
            resized = self._resized(target)
            self._compile_behind(resized, held)
            self._resize(resized, held)
        elif capacity not in self._compiled:         # constant velocity until it compiles
            if holding:
                self._resize(self._resized(holding[0]), held, "; compiled")
            else:
                self._compile_behind(self.state, held)
        else:
            self._shrink(held, needed)

    def _shrink(self, held: int, needed: int) -> None:
        """Count the frames in a row whose tracks, before and after the step (`needed`), fit a
        smaller bucket, and the most over them; after `shrink_after` of them, move to the
        bucket of that most, compacted, once its program is compiled (in the background
        meanwhile)."""
        capacity = self.state.capacity
        if bucket_size(needed) >= capacity or capacity <= self._floor:
            self._small_frames, self._small_peak = 0, 0
            return
        self._small_frames += 1
        self._small_peak = max(self._small_peak, needed)
        if self.shrink_after is None or self._small_frames < self.shrink_after:
            return
        smaller = self._resized(max(bucket_size(self._small_peak), self._floor))
        if smaller.capacity in self._compiled or self._compiles_inline():
            self._resize(smaller, held, f"; at most {self._small_peak} for "
                                        f"{self._small_frames} frames")
        else:
            self._compile_behind(smaller, held)

    def _resize(self, resized: StreamState, held: int, why: str = "") -> None:
        """Take the state `_resized` gave, and say so (with `why`)."""
        logger.info("frame %d: capacity %d -> %d slots (%d tracks%s)", self.frames,
                    self.state.capacity, resized.capacity, held, why)
        self.state = resized
        self._small_frames, self._small_peak = 0, 0

    def _held_after(self, ids: np.ndarray, lost: np.ndarray, idle: int) -> int:
        """The tracks the state holds after `idle` empty steps and this frame (`observe`'s
        slots): those seen in the history still kept, less the lost, plus the new ids."""
        track_ids = np.asarray(self.state.track_ids)
        kept = ((track_ids != FREE) & np.asarray(self.state.detected)[:, 1 + idle:].any(axis=1)
                & ~np.isin(track_ids, lost))
        return int(kept.sum() + np.isin(ids, track_ids[kept], invert=True).sum())

    def _compile_behind(self, state: StreamState, held: int) -> None:
        """Compile the step at `state`'s capacity in the background (one compile at a time),
        where the loop must not wait for it; a capacity the crowd grew into is announced
        once, with what the wait was for the compiles so far. A capacity whose compiling
        the memory cannot hold is refused here, in one line (`DataError`)."""
        capacity = state.capacity
        if (self._compiles_inline() or capacity in self._compiled or capacity in self._failed
                or self._compiling is not None):
            return
        what = f"a stream step over {capacity} slots"
        check_compiler_room(what)
        if capacity > self.state.capacity:
            slowest = max(self._compiled.values())
            logger.warning(
                "frame %d: %d tracks need %d slots, beyond the capacities compiled (%s): %s "
                "compiles in the background, and constant velocity predicts until it is done "
                "(StreamOutput.fallback \"compiling\"): about %.1f s, this stream's slowest "
                "compile so far (longer where that came from the compilation cache); "
                "Stream.warm_up(%d) compiles it ahead", self.frames, held, capacity,
                ", ".join(map(str, sorted(self._compiled))), what, slowest, held)
        args = self._args(jax.tree.map(np.array, _host_tree(state)), np.zeros(0, np.int32),
                          np.zeros((0, 2)), np.zeros(0, np.int32))
        self._compiling = (capacity, _compiler().submit(
            _compile, self._step, args, self._checked_config(), self.grid.step_s,
            " in the background"))

    def _collect_compile(self) -> None:
        """Take the background compile that has finished: its program is this stream's; a
        refusal (memory) is raised here, another failure logged, that capacity not tried
        again."""
        if self._compiling is None or not self._compiling[1].done():
            return
        capacity, job = self._compiling
        self._compiling = None
        try:
            self._compiled[capacity] = job.result()
        except DataError:
            raise
        except Exception as error:           # constant velocity while it is needed
            self._failed.add(capacity)
            self._error = (f"compiling the step over {capacity} slots failed: "
                           f"{type(error).__name__}: {str(error).splitlines()[0][:300]}")
            logger.error("frame %d: %s; constant velocity predicts while the crowd needs them",
                         self.frames, self._error)

    def _finish_compiling(self) -> None:
        """Wait for the background compile, if any, and take it (`_collect_compile`)."""
        if self._compiling is not None:
            self._compiling[1].exception()
            self._collect_compile()

    def _constant_velocity(self, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray,
                           idle: int) -> tuple:
        """The step without the model, in numpy (`gst_jax.stream_fallback`): the tracks move
        on as the core's step moves them, nothing is scored, every track detected at the last
        two steps is predicted at constant velocity, with the radii in force."""
        state = _host_tree(self.state)
        gate = None if self.gate is None else self.gate.in_steps(self.grid.step_s)
        nobody = np.zeros(0, np.int32)
        for step_ids in [nobody] * idle + [ids]:
            state = stream_fallback.observe(state, step_ids, positions[:len(step_ids)], lost,
                                            gate)
            state = stream_fallback.skip_scoring(state, self.regions, self._fresh_regions)
        pred_len = self.grid.pred_len
        samples = self.model.num_samples if isinstance(self.model, StreamModel) else 1
        futures, predicted = stream_fallback.constant_velocity(
            state, pred_len, 1 if self.mean else samples)
        delayed = None if self.regions is None else stream_fallback.nothing_scored(
            state.capacity, pred_len)
        return (state, futures, predicted,
                stream_fallback.radii_in_force(state, self.regions, pred_len), delayed)

    def _note_fallback(self, reason: str | None) -> None:
        """Count a frame predicted by constant velocity, and log where that starts or ends."""
        if reason is not None:
            self.fallbacks += 1
        if reason == self._fallback:
            return
        if reason is None:
            logger.info("frame %d: the model predicts again, after %d frames of constant "
                        "velocity", self.frames, self.frames - self._fallback_since)
        else:
            why = {"compiling": f"the step over {self.state.capacity} slots is compiling in "
                                "the background",
                   "overrun": f"the model's step is not done after {self.deadline_s} s "
                              "(deadline_s)",
                   "error": self._error}[reason]
            logger.warning("frame %d: constant velocity predicts: %s", self.frames, why)
            self._fallback_since = self.frames
        self._fallback = reason

    def _resized(self, capacity: int) -> StreamState:
        """The same tracks in `capacity` slots, numpy on the host (resizing compiles nothing):
        growing adds free slots at the end (per track, with fresh regions); shrinking compacts
        the tracks into the first slots, in their order, each slot's history, flags, score
        buffer, per-slot conformal state and issued predictions moving with it."""
        state = _host_tree(self.state)
        free = state.track_ids == FREE
        order = np.concatenate([np.flatnonzero(~free), np.flatnonzero(free)])
        keep = order[:capacity] if capacity < state.capacity else np.arange(state.capacity)
        assert (~free).sum() <= capacity, "a stream shrinks only to hold its tracks"
        extra = capacity - len(keep)

        def slots(array, axis=0, value=0):
            widths = [(0, 0)] * array.ndim
            widths[axis] = (0, extra)
            return np.pad(np.take(array, keep, axis=axis), widths, constant_values=value)

        resized = state.replace(track_ids=slots(state.track_ids, value=FREE),
                                positions=slots(state.positions),
                                detected=slots(state.detected), fresh=slots(state.fresh),
                                restarted=slots(state.restarted))
        if self.adaptation is not None:       # issued predictions: (P, C, ...) per slot
            resized = resized.replace(adaptation=state.adaptation._replace(
                issued=jax.tree.map(lambda a: slots(a, 1), state.adaptation.issued)))
        if self.regions is None:
            return resized
        feed = state.feed._replace(predicted=slots(state.feed.predicted, 1),
                                   valid=slots(state.feed.valid, 1),
                                   issued=slots(state.feed.issued, 1))
        regions = state.regions
        if regions is not None and not self.regions.pooled:
            regions = jax.tree.map(
                lambda old, new: np.concatenate([old[keep], np.repeat(new, extra, axis=0)]),
                regions, self._fresh_regions)
        return resized.replace(feed=feed, regions=regions)

    # --- Saved and restored: a restarted robot's warm tracks and discs ---------------------

    # What a saved stream keeps of the host beside its state: each attribute and how the file
    # holds it (`gst_jax.stream_file`). An attribute the host adds that outlives a step is one
    # more line here.
    _KEPT = {
        "frames": stream_file.COUNT,
        "restarts": stream_file.COUNT,
        "_lost": stream_file.TRACK_IDS,
        "_clock": stream_file.Kept(Clock.as_json, Clock.from_json),
        "key": stream_file.KEY,
        "_floor": stream_file.COUNT,
        "_small_frames": stream_file.COUNT,
        "_small_peak": stream_file.COUNT,
        "fallbacks": stream_file.COUNT,
        "overruns": stream_file.COUNT,
    }

    def save(self, path: str | Path) -> Path:
        """Write the tracks (their histories, score buffer, conformal and adaptation states)
        and the host's fields (`_KEPT`: frames, clock, key, ...) to one safetensors file,
        atomically (written beside it, then renamed: a crash leaves the last save whole);
        returns its path. `load` resumes from it."""
        host = {name: kept.write(getattr(self, name)) for name, kept in self._KEPT.items()}
        return stream_file.write(path, _host_tree(self.state), self._identity(), host)

    def load(self, path: str | Path) -> Stream:
        """This stream, holding what `save` wrote to `path`: from now on it steps as the saved
        stream would have, bit for bit (its key and frame count are the saved ones; `seed`
        no longer counts; its capacity is the saved one's). Built as the saved stream was (the
        same model and parameters, step, regions, adaptation and robot), or the file is
        refused in one line naming what differs (`DataError`), as a damaged file is
        (`gst_jax.stream_file`). max_speed, non_finite and compilation_cache are this one's.

            stream = Stream(run, regions=Regions("dtaci", 0.1)).load("stream.safetensors")
        """
        state, host = stream_file.read(path, self._identity(), self._empty_state, self._KEPT)
        self.state = state
        for name, value in host.items():
            setattr(self, name, value)
        return self

    def _identity(self) -> dict:
        """What this stream's tracks are of: a file of another's is refused on loading."""
        return {"predictor": repr(self.model),
                "params_sha256": stream_file.params_digest(self.params),
                "step_s": self.grid.step_s, "regions": repr(self.regions),
                "adaptation": repr(self.adaptation), "robot": self.robot}

    def _empty_state(self, capacity: int) -> StreamState:
        """The shapes and dtypes of this stream's state at `capacity` slots (nothing
        computed)."""
        return jax.eval_shape(lambda: init_state(capacity, self.grid.obs_len, self.regions,
                                                 self.grid.pred_len, self.adaptation))


# `init_state` as one program (a few hundredths of a second from a warm compilation cache)
# rather than two dozen eager operations, each traced and compiled or loaded on its own.
_initial_state = jax.jit(init_state, static_argnums=(0, 1, 2, 3, 4))


def _predictor_grid(predictor: ConstantVelocity | Standing, step_s) -> TimeGrid:
    """The time grid of a predictor without a model, checked by TimeGrid's rules."""
    if step_s is None:
        raise DataError(f"Stream: {type(predictor).__name__} needs step_s, the seconds between "
                        "its steps (e.g. Stream(ConstantVelocity(obs_len=8, pred_len=12), "
                        "step_s=0.4))")
    grid = TimeGrid(step_s, predictor.obs_len, predictor.pred_len)
    try:
        check_config(grid, tuple(rules(grid)))
    except ValueError as error:
        raise DataError(f"Stream: {error}") from None
    if grid.obs_len < 2:
        raise DataError(f"Stream: {type(predictor).__name__} needs obs_len of 2 or more (a "
                        f"displacement), got {grid.obs_len}")
    return grid


def _compile(step: Any, args: tuple, config, step_s: float, where: str) -> float:
    """Compile the jitted `step` for `args` (its capacity's program, which jit's cache then
    holds), checked first where `config` is a gst_jax model's (`compile_checked`: memory, a
    large crowd; issue 78); logged, and returns its seconds."""
    capacity = args[1].capacity
    what = f"a stream step over {capacity} slots"
    started = perf_counter()
    if config is None:
        step.trace(*args).lower().compile()
    else:
        compile_checked(step, args, config, capacity, what, slower_than_s=step_s)
    seconds = perf_counter() - started
    logger.info("compiled %s in %.1f s%s", what, seconds, where)
    return seconds


@functools.cache
def _compiler() -> ThreadPoolExecutor:
    """The thread that compiles streams' programs in the background, one at a time (each
    takes the cores it finds)."""
    return ThreadPoolExecutor(1, thread_name_prefix="gst_jax.stream.compile")


def _call(step: Callable, args: tuple) -> tuple:
    """The jitted step on `args`: the state (on the device) and the outputs as numpy."""
    state, *outputs = step(*args)
    return (state, *_host_tree(outputs))


def _gate_limit(name: str, value, must_be: str, least: float | None = None) -> float | None:
    """One of the gate's numbers (`Stream`'s max_speed, ...) as a float (None stays None where
    `least` is None), or a one-line refusal: finite and above 0, or at least `least`."""
    if value is None and least is None:
        return None
    number = float(value) if isinstance(value, numbers.Real) else math.nan
    if not (math.isfinite(number) and (number > 0 if least is None else number >= least)):
        raise DataError(f"Stream: {name} must be {must_be}, got {value!r}")
    return number


def _host_tree(tree):
    """Every array of a pytree as numpy (None stays None)."""
    return jax.tree.map(np.asarray, tree)


def _checked_frame(ids, positions, non_finite: str = "raise") -> tuple[np.ndarray, np.ndarray]:
    """A frame's ids (M,) and positions (M, 2), or a one-line refusal; with non_finite
    "undetected", the people whose position is not finite left out."""
    ids = np.asarray(ids)
    positions = np.asarray(positions)
    if ids.ndim != 1:
        raise DataError(f"a frame's ids must be (M,), got shape {ids.shape}")
    if positions.shape != (len(ids), 2) and not (len(ids) == 0 and positions.size == 0):
        raise DataError(f"a frame of {len(ids)} ids needs positions ({len(ids)}, 2): one "
                        f"(x, y) row per id; got shape {positions.shape}")
    if not np.issubdtype(positions.dtype, np.number):
        raise DataError(f"a frame's positions must be numbers, got {positions.dtype}")
    positions = positions.astype(np.float64).reshape(len(ids), 2)
    if len(ids) and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0
                     or ids.max() >= Stream.ROBOT):
        raise DataError(f"track ids must be integers from 0 to {Stream.ROBOT - 1}, got "
                        f"{ids[:5].tolist()}...")
    if len(np.unique(ids)) != len(ids):
        values, counts = np.unique(ids, return_counts=True)
        raise DataError(f"track id {values[counts > 1][0]} appears twice in one frame")
    finite = np.isfinite(positions).all(axis=1)
    if not finite.all() and non_finite == "raise":
        index = int(np.flatnonzero(~finite)[0])
        raise DataError(f"track {ids[index]}'s position is {positions[index].tolist()}: not "
                        "finite (leave an undetected person out of the frame, or "
                        "Stream(non_finite=\"undetected\"))")
    far = finite & (np.abs(np.where(np.isfinite(positions), positions, 0)).max(
        axis=1, initial=0) > LARGEST_COORDINATE)
    if far.any():
        index = int(np.flatnonzero(far)[0])
        raise DataError(f"track {ids[index]}'s position {positions[index].tolist()} lies "
                        f"beyond {LARGEST_COORDINATE:.0e} m, where float32 loses millimetres: "
                        "subtract a local origin first")
    return ids[finite].astype(np.int32), positions[finite]


if __name__ == "__main__":      # python -m gst_jax.stream replay ...: the stream's commands
    from gst_jax.stream_commands import main

    main()
