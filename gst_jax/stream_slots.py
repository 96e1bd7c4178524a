"""The slots a stream's tracks live in, of a capacity that follows the crowd, and each frame's
step over them, by the model where it is in time, else by constant velocity: what keeps a
robot's loop going whatever the crowd does (`gst_jax.stream.Stream` holds one, `Slots`).

    slots = Slots(model, params, key, grid, regions=..., adaptation=..., gate=..., mean=True,
                  capacity=8, deadline_s=0.25, shrink_after=20)
    state, futures, predicted, radii, delayed = slots.advance(ids, positions, idle)

The capacity follows the crowd by the buckets of `gst_jax.data.bucket_size`, so that a crowd
that changes size meets few compiled programs: it grows at once, and shrinks (the tracks
compacted, with their histories, score buffer, per-slot conformal states and issued
predictions) once they have fitted a smaller bucket for `shrink_after` frames in a row. Each
capacity is one program (`gst_jax.stream_programs`: compiled before its first step, in the
background where the loop has a deadline; `warm_up` compiles them ahead). A frame the model
cannot predict in time (its program still compiling, a step past the deadline or one that
failed) gets constant velocity, computed on the host with the tracks kept whole
(`gst_jax.stream_fallback`; why: `Slots.fallback`). Capacity changes and fallbacks are
logged (logger "gst_jax.stream").
"""

from __future__ import annotations

import logging

import jax
import numpy as np

from gst_jax import stream_fallback
from gst_jax.adaptation import Adaptation
from gst_jax.config import TimeGrid
from gst_jax.conformal import Regions
from gst_jax.data import bucket_size
from gst_jax.errors import DataError
from gst_jax.model import Params
from gst_jax.predict import check_compiler_room
from gst_jax.predictors import ConstantVelocity, Standing
from gst_jax.stream_core import FREE, Frame, Gate, StreamModel, StreamState, init_state
from gst_jax.stream_programs import Programs

logger = logging.getLogger("gst_jax.stream")


class Slots:
    """A stream's tracks (`state`, a `StreamState` of `state.capacity` slots) and each frame's
    step over them (the module docstring): `advance` moves them one model step on, by the
    model within `deadline_s` or by constant velocity, the tracks of the ids in `lost` (those
    a tracker reported lost, or restarted) ended first; `frames` counts the steps (the key of
    step t folds in t), `fallbacks` the frames constant velocity predicted.

    model, params, key, grid, regions, adaptation, gate, mean: the stream's (`Stream`; the
    gate in metres and seconds). capacity: the first (a bucket size), the smallest it shrinks to.
    deadline_s: seconds a frame waits for the model; None: every frame waits, compiling
    included. shrink_after: frames in a row whose tracks fit a smaller bucket before the
    capacity shrinks to it; None: never."""

    def __init__(self, model: StreamModel | ConstantVelocity | Standing, params: Params | None,
                 key: jax.Array, grid: TimeGrid, *, regions: Regions | None,
                 adaptation: Adaptation | None, gate: Gate | None, mean: bool, capacity: int,
                 deadline_s: float | None, shrink_after: int | None):
        self.model, self.params, self.key, self.grid = model, params, key, grid
        self.regions, self.adaptation, self.gate, self.mean = regions, adaptation, gate, mean
        self.frames = 0              # model steps so far (the key of step t folds in t)
        self.lost: set[int] = set()  # ids whose tracks end at the next step
        self.state = _initial_state(capacity, grid.obs_len, regions, grid.pred_len, adaptation)
        # Per track, the regions of one fresh slot, to give the slots a growing stream adds.
        self._fresh_regions = None if regions is None or regions.pooled else _host_tree(
            regions.init(1, grid.pred_len))
        # Each capacity's program, compiled inline or in the background, run in time.
        self._programs = Programs(model, regions, gate, adaptation, grid.step_s, deadline_s)
        self.shrink_after = shrink_after
        self._floor = self.state.capacity       # the smallest capacity it shrinks to
        # Frames in a row whose tracks fitted a smaller bucket, and the most tracks over them.
        self._small_frames, self._small_peak = 0, 0
        self.fallbacks = 0           # frames predicted by constant velocity (`FALLBACKS`)
        self.fallback: str | None = None         # why the last step's predictions are CV's
        self._fallback_since, self._error = 0, ""

    @property
    def overruns(self) -> int:
        """Model steps that took longer than the model's period (`Programs.overruns`)."""
        return self._programs.overruns

    def advance(self, ids: np.ndarray, positions: np.ndarray, idle: int = 0) -> tuple:
        """One model step over a checked frame (ids (M,), positions (M, 2)), after `idle`
        steps where nobody was detected (run without the model), the tracks of `lost` ended
        before it, in a state of the capacity its tracks need (`_fit`): the state moves on;
        returns it and the step's outputs as numpy arrays. Where the model cannot give this
        frame's predictions in time, constant velocity gives them, on the host
        (`_constant_velocity`; why: `self.fallback`, `StreamOutput.fallback`)."""
        lost = np.zeros(0, np.int32)
        if self.lost:
            held = set(np.asarray(self.state.track_ids).tolist())
            lost = np.array(sorted(self.lost & held), np.int32)
            self.lost.clear()
        self._fit(ids, lost, idle)
        reason, outcome = self._model_step(ids, positions, lost, idle)
        if outcome is None:
            outcome = self._constant_velocity(ids, positions, lost, idle)
        self._note_fallback(reason)
        self.state, self.frames = outcome[0], self.frames + 1 + idle
        return outcome

    def warm_up(self, largest: int, max_compile_s: float | None) -> tuple[int, ...]:
        """Compile the step of every capacity from this one up to `largest` (a bucket size),
        on the tracks as they are (the outputs unkept), and return them; the state is left as
        it was. The largest compiles first, so that what cannot be afforded is refused in one
        line (`DataError`) before the rest: a step the memory cannot hold (`compile_checked`),
        or compiles expected to take longer than `max_compile_s` in all (None: no bound), at
        the largest's seconds each."""
        capacities = [self.state.capacity]
        while capacities[-1] < largest:
            capacities.append(bucket_size(capacities[-1] + 1))
        state, programs = self.state, self._programs
        try:
            for capacity in (capacities[-1], *capacities[:-1]):
                self.state = state
                self.state = self._resized(capacity)
                args = self._args(self.state, np.zeros(0, np.int32), np.zeros((0, 2)),
                                  np.zeros(0, np.int32))
                if capacity == capacities[-1] and capacity not in programs.compiled:
                    programs.compile_inline(args)
                    _check_compile_time(capacities, programs.compiled, max_compile_s)
                programs.run(args)
        finally:
            self.state = state
        return tuple(capacities)

    def fill(self, ids: np.ndarray, ticks: np.ndarray, positions: np.ndarray, first: int
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

    def empty_state(self, capacity: int) -> StreamState:
        """The shapes and dtypes of the state at `capacity` slots (nothing computed)."""
        return jax.eval_shape(lambda: init_state(capacity, self.grid.obs_len, self.regions,
                                                 self.grid.pred_len, self.adaptation))

    def _model_step(self, ids: np.ndarray, positions: np.ndarray, lost: np.ndarray,
                    idle: int) -> tuple[str | None, tuple | None]:
        """(None, the model's step) or (why not, None): "compiling" (this capacity's program
        compiles in the background), "overrun" (this step, or an earlier one still running,
        took longer than `deadline_s`), "error" (it raised; logged)."""
        capacity, programs = self.state.capacity, self._programs
        if capacity not in programs.compiled and not programs.inline():
            return ("error" if capacity in programs.failed else "compiling"), None
        if programs.busy():
            return "overrun", None
        try:
            outcome = programs.run_in_time(self._args(self.state, ids, positions, lost, idle))
        except DataError:
            raise                            # a refusal (memory), with its fix: the user's
        except Exception as error:           # any other failure: the robot goes on, on CV
            self._error = (f"the model's step failed: {type(error).__name__}: "
                           f"{str(error).splitlines()[0][:300]}")
            logger.debug("the model's step at frame %d failed", self.frames, exc_info=True)
            return "error", None
        return ("overrun", None) if outcome is None else (None, outcome)

    def _args(self, state: StreamState, ids: np.ndarray, positions: np.ndarray,
              lost: np.ndarray, idle: int = 0) -> tuple:
        """The jitted step's arguments: the frame padded to the state's capacity."""
        width = state.capacity
        frame = Frame(np.pad(ids, (0, width - len(ids)), constant_values=FREE),
                      np.pad(positions, [(0, width - len(ids)), (0, 0)]).astype(np.float32),
                      np.pad(lost, (0, width - len(lost)), constant_values=FREE))
        return (self.params, state, frame, self.key, np.int32(self.frames), np.int32(idle))

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
        compiled = self._programs.compiled
        holding = sorted(c for c in compiled if c >= needed)
        if held > capacity:
            target = holding[0] if holding else bucket_size(held)
            resized = self._resized(target)
            self._compile_behind(resized, held)
            self._resize(resized, held)
        elif capacity not in compiled:               # constant velocity until it compiles
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
        if smaller.capacity in self._programs.compiled or self._programs.inline():
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
        capacity, programs = state.capacity, self._programs
        if (programs.inline() or capacity in programs.compiled or capacity in programs.failed
                or programs.compiling is not None):
            return
        what = f"a stream step over {capacity} slots"
        check_compiler_room(what)
        if capacity > self.state.capacity:
            slowest = max(programs.compiled.values())
            logger.warning(
                "frame %d: %d tracks need %d slots, beyond the capacities compiled (%s): %s "
                "compiles in the background, and constant velocity predicts until it is done "
                "(StreamOutput.fallback \"compiling\"): about %.1f s, this stream's slowest "
                "compile so far (longer where that came from the compilation cache); "
                "Stream.warm_up(%d) compiles it ahead", self.frames, held, capacity,
                ", ".join(map(str, sorted(programs.compiled))), what, slowest, held)
        programs.compile_behind(self._args(jax.tree.map(np.array, _host_tree(state)),
                                           np.zeros(0, np.int32), np.zeros((0, 2)),
                                           np.zeros(0, np.int32)))

    def _collect_compile(self) -> None:
        """Take the background compile that has finished (`Programs.collect`): a refusal
        (memory) is raised here, another failure logged, that capacity not tried again."""
        failure = self._programs.collect()
        if failure is not None:              # constant velocity while it is needed
            self._error = failure
            logger.error("frame %d: %s; constant velocity predicts while the crowd needs them",
                         self.frames, self._error)

    def _finish_compiling(self) -> None:
        """Wait for the background compile, if any, and take it (`_collect_compile`)."""
        if self._programs.compiling is not None:
            self._programs.compiling[1].exception()
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
        if reason == self.fallback:
            return
        if reason is None:
            logger.info("frame %d: the model predicts again, after %d frames of constant "
                        "velocity", self.frames, self.frames - self._fallback_since)
        else:
            why = {"compiling": f"the step over {self.state.capacity} slots is compiling in "
                                "the background",
                   "overrun": f"the model's step is not done after "
                              f"{self._programs.deadline_s} s (deadline_s)",
                   "error": self._error}[reason]
            logger.warning("frame %d: constant velocity predicts: %s", self.frames, why)
            self._fallback_since = self.frames
        self.fallback = reason

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


# `init_state` as one program (a few hundredths of a second from a warm compilation cache)
# rather than two dozen eager operations, each traced and compiled or loaded on its own.
_initial_state = jax.jit(init_state, static_argnums=(0, 1, 2, 3, 4))


def _host_tree(tree):
    """Every array of a pytree as numpy (None stays None)."""
    return jax.tree.map(np.asarray, tree)


def _check_compile_time(capacities: list[int], compiled: dict[int, float],
                        max_compile_s: float | None) -> None:
    """Refuse in one line where compiling the `capacities` not compiled before (the largest,
    just compiled, and those not yet), each in the seconds the largest took, is expected to
    take longer than `max_compile_s`."""
    programs = 1 + sum(capacity not in compiled for capacity in capacities)
    seconds = compiled[capacities[-1]]
    if max_compile_s is None or seconds * programs <= max_compile_s:
        return
    raise DataError(f"warm_up: {capacities[-1]} slots take {programs} programs (capacities "
                    f"{capacities[0]} to {capacities[-1]}), about {seconds * programs:.0f} s "
                    f"at the {seconds:.1f} s the largest took, beyond max_compile_s="
                    f"{max_compile_s:g}; warm up to the crowd you expect, or give a larger "
                    "max_compile_s (None: no bound)")

