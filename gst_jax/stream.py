"""Prediction over a tracker's output, one frame at a time: what a robot runs.

    stream = Stream(load_model("pretrained:crowdnav_sim"))
    out = stream.step(track_ids, positions)             # the people detected now
    out.ids, out.futures                                 # (L,), (L, P, 2) or (L, K, P, 2)

Each track keeps its last `obs_len` positions with a detection mask in a slot of a fixed
capacity, as a window's pedestrians do: a track that appears is partially detected (GST's
point: it is predicted from the steps it was seen), one unseen for `obs_len` steps is dropped
and its slot reused. The capacity follows the crowd (`gst_jax.stream_slots`): it grows at
once, and shrinks once the tracks have fitted a smaller bucket for `SHRINK_AFTER` frames in a
row; `Stream.warm_up` compiles its programs before the robot moves, `compilation_cache=DIR`
keeps them for the next process. A frame the model cannot predict in time (a program still
compiling, in the background; a step past its deadline, or failed) gets constant velocity,
with the tracks kept whole (`StreamOutput.fallback`), and the loop goes on. Compiles, capacity
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
A frame further after the last than `max_gap_s` (by default obs_len + pred_len steps, beyond
which nothing of the tracks is left) is refused, the stream unchanged: a stray timestamp, or
times in milliseconds; after a real pause, the next frame starts the tracks afresh.

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

One job, though over 400 lines: the host class, of which most lines are its docstrings (each
setting a robot's engineer chooses, with its default and why); its code is a thin layer over
`stream_core`, `stream_slots`, `stream_time` and `stream_file`.
"""

from __future__ import annotations

import numbers
import operator
from pathlib import Path

import jax
import numpy as np

from gst_jax import stream_checks, stream_file, stream_output
from gst_jax.adaptation import Adaptation
from gst_jax.compiles import use_persistent_cache
from gst_jax.conformal import Regions
from gst_jax.data import bucket_size
from gst_jax.errors import DataError
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
from gst_jax.stream_output import StreamOutput
from gst_jax.stream_slots import Slots
from gst_jax.stream_time import Clock, Jumps

__all__ = [
    # the host: numpy in and out, ids, capacity growth, times, compiling ahead
    "Stream", "StreamOutput", "MAX_SPEED", "MAX_ACCELERATION", "JUMP_TOLERANCE", "NON_FINITE",
    "SHRINK_AFTER", "DEADLINE_S", "FALLBACKS",
    # re-exported: the pure core (gst_jax.stream_core) and the regions (gst_jax.conformal)
    "FREE", "Frame", "Gate", "StreamModel", "StreamState", "adapt", "as_batch", "init_state",
    "make_step", "observe", "predict_slots", "update_regions", "Regions",
]

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
# `warm_up`'s bound on its compiles, in all: a choice (10 min), above the slowest warm-up
# measured for a robot's crowd (crowd_d to 64 people on a loaded 2-core VM, docs/robot.md) and
# far below the hours a mistyped size would take (issue 94: warm_up(10**6) compiled 57
# programs in 7 minutes of 31,250).
WARM_UP_COMPILE_S = 600.0
# Why constant velocity, not the model, predicted a frame (`StreamOutput.fallback`): the
# program of the capacity the crowd needs compiles in the background; the model's step took
# longer than the deadline (or an earlier one that did still runs); the model's step failed.
FALLBACKS = ("compiling", "overrun", "error")


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
    max_gap_s: the longest a timed frame may come after the last one (seconds; "horizon",
    the default: obs_len + pred_len model steps, beyond which nothing of the tracks is left to
    predict or score; at most 2**16 steps). A frame further on is refused in one line
    (`gst_jax.stream_time.FrameGap`, a `DataError`, which a caller may skip) and changes
    nothing: a stray timestamp (1e9 after 0) or times in milliseconds (a 10 Hz tracker's
    frames 100 apart) never reach the clock. Where the tracker did pause so long, the next
    frame within max_gap_s after the refused one confirms the jump and is taken: the tracks
    start afresh from it (the steps between run as a gap beyond the horizon does).
    Compiles (with their seconds), capacity changes, overruns and constant velocity's frames
    are logged (`logging`, logger "gst_jax.stream"); nothing is printed.
    """

    # The robot's id among the tracks: no tracker's.
    ROBOT = stream_checks.ROBOT

    def __init__(self, run, *, num_samples: int = 1, mean: bool = True, capacity: int = 8,
                 seed: int = 0, convention: str = "gst", regions: Regions | None = None,
                 robot: bool = False, max_speed: float | None = MAX_SPEED,
                 non_finite: str = "raise", compilation_cache: str | None = None,
                 adaptation: Adaptation | None = None,
                 max_acceleration: float | None = MAX_ACCELERATION,
                 jump_tolerance: float = JUMP_TOLERANCE, step_s: float | None = None,
                 deadline_s: float | str | None = "default",
                 shrink_after: int | None = SHRINK_AFTER, max_gap_s: float | str = "horizon"):
        if deadline_s == "default":
            deadline_s = DEADLINE_S
        if not (isinstance(non_finite, str) and non_finite in NON_FINITE):
            raise DataError(f"Stream: non_finite must be one of {NON_FINITE}, got "
                            f"{non_finite!r}")
        if regions is not None and not isinstance(regions, Regions):
            raise DataError(f"Stream: regions must be gst_jax.conformal.Regions (e.g. "
                            f"Regions(\"dtaci\", alpha=0.1)) or None, got "
                            f"{type(regions).__name__} {str(regions)[:60]!r}")
        gate = stream_checks.checked_gate(max_speed, max_acceleration, jump_tolerance)
        stream_checks.check_timing(deadline_s, shrink_after)
        if compilation_cache is not None:
            use_persistent_cache(compilation_cache)
        self.model, self.params, self.mean, self.grid = stream_checks.predictor(
            run, num_samples, mean, convention, step_s)
        # Frames that come too long after the last: refused, or taken as a jump confirmed.
        self._jumps = Jumps(stream_checks.checked_max_gap(max_gap_s, self.grid),
                            (self.grid.obs_len + self.grid.pred_len) * self.grid.step_s)
        self.regions, self.robot, self.adaptation = regions, robot, adaptation
        self.max_speed = None if max_speed is None else float(max_speed)
        self.gate, self.non_finite = gate, non_finite
        self.restarts = 0            # tracks restarted so far (`StreamOutput.restarted`)
        config = self.grid
        # Frame times resampled to the model's steps (`step(..., time=)`); with the slots and
        # the counters above, all a stream holds between frames.
        self._clock = Clock(config.step_s)
        # The tracks in slots of the capacity they need, those to end at the next step, the
        # key, the model's step with its programs and deadline, constant velocity where it is
        # late (`gst_jax.stream_slots`).
        self._slots = Slots(self.model, self.params, jax.random.key(seed), config,
                            regions=regions, adaptation=adaptation, gate=gate, mean=self.mean,
                            capacity=bucket_size(capacity),
                            deadline_s=(config.step_s if deadline_s == "step" else
                                        None if deadline_s is None else float(deadline_s)),
                            shrink_after=shrink_after)

    @property
    def state(self) -> StreamState:
        """The tracks (`StreamState`), in the slots of the capacity they need."""
        return self._slots.state

    @state.setter
    def state(self, state: StreamState) -> None:
        self._slots.state = state

    @property
    def frames(self) -> int:
        """Model steps so far (the key of step t folds in t)."""
        return self._slots.frames

    @property
    def fallbacks(self) -> int:
        """Frames predicted by constant velocity (`FALLBACKS`)."""
        return self._slots.fallbacks

    @property
    def overruns(self) -> int:
        """Model steps that took longer than the model's period."""
        return self._slots.overruns

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
        or before the last one's time is (`DataError`), or more than `max_gap_s` after it
        (unless it confirms a jump: see the class), or at a time that cannot be seconds, each
        leaving the stream as it was. A track missing from a frame is filled in once seen
        again within two steps; steps where nobody was seen (a gap) run at once, without the
        model. Without time, a frame is one model step after the last."""
        ids, positions = stream_checks.checked_frame(ids, positions, self.non_finite)
        if self.robot:
            ids, positions = stream_checks.with_robot(ids, positions, robot_xy)
        clock = self._clock
        if time is None and clock.last_time is not None:       # a timed stream
            time = clock.last_time + clock.step_s
        horizon = self.grid.obs_len + self.grid.pred_len
        afresh = False
        if time is not None:
            time = clock.checked_time(time)
            afresh = self._jumps.confirmed(time, clock.last_time, clock.step_s)
        self._check_count(1 if time is None else 1 + horizon if afresh
                          else clock.ticks_reached(time))
        if lost is not None:
            self.forget(lost)
        if time is None:
            return self._output([self._slots.advance(ids, positions)])
        if afresh:      # a new clock from this frame, after the steps of a gap beyond horizon
            self._clock = clock = Clock(clock.step_s)
        first = clock.ticks
        reached = clock.frame(time, ids, positions, self.gate)
        filled_ids, filled_ticks, filled_xy = reached.fills
        self._slots.fill(filled_ids, filled_ticks, filled_xy, first)
        if len(reached.restarted):     # their old tracks end at the next step, as forgotten
            self._slots.lost.update(reached.restarted.tolist())
        steps, idle = [], horizon if afresh else 0
        for n, tick in enumerate(reached.ticks):
            if len(tick.ids) == 0 and n < len(reached.ticks) - 1:
                idle += 1
                continue
            # Beyond obs_len + pred_len empty steps nothing is left to predict or to score.
            skipped = max(0, idle - self.grid.obs_len - self.grid.pred_len)
            self._slots.frames += skipped
            steps.append(self._slots.advance(tick.ids, tick.positions, idle - skipped))
            idle = 0
        if not steps:
            return self._repeated(reached.restarted, time)
        return self._output(steps, reached.restarted, reached.ticks[-1].time,
                            len(reached.ticks))

    def _check_count(self, steps: int) -> None:
        """Refuse, in one line, a frame whose `steps` model steps would take the step count
        past what its int32 holds (the key of step t folds in t; a saved stream keeps it)."""
        if self.frames + steps > stream_file.MAX_COUNT:
            raise DataError(f"a frame of {steps} model step(s) would take this stream past "
                            f"{stream_file.MAX_COUNT} steps, the most its step count (int32) "
                            "holds: start a new Stream")

    def _output(self, steps: list[tuple], restarted: np.ndarray | None = None,
                time: float | None = None, ticks: int = 1) -> StreamOutput:
        """The output of the last of a frame's model steps (`Slots.advance`'s), with the tracks
        restarted at any of them or before (`restarted`, the raw detections' restarts)."""
        restarted = np.zeros(0, np.int32) if restarted is None else restarted
        output = stream_output.predicted(steps[-1], self.ROBOT, self.mean,
                                         self._restarted(steps, restarted, time), time, ticks,
                                         self._slots.fallback)
        self._clock.last_output = {"ids": output.ids, "futures": output.futures,
                                   "radii": output.radii}
        return output

    def _repeated(self, restarted: np.ndarray, time: float) -> StreamOutput:
        """A frame that reached no model step: the last step's predictions again (ticks 0),
        nothing scored."""
        clock = self._clock
        assert clock.last_output is not None, "the first frame reaches its step"
        scored = None if self.regions is None else (self.state.capacity, self.grid.pred_len)
        return stream_output.repeated(clock.last_output, scored,
                                      self._restarted([], restarted, time),
                                      clock.tick_time(clock.ticks - 1), self._slots.fallback)

    def _restarted(self, steps: list[tuple], before: np.ndarray, time: float | None
                   ) -> np.ndarray:
        """The tracks restarted at a frame (`stream_output.restarted`), counted."""
        ids = stream_output.restarted(steps, before, self.ROBOT, time)
        self.restarts += len(ids)
        return ids

    def forget(self, ids) -> None:
        """End the tracks of these ids (a tracker's lost tracks) at the next step, before that
        frame's detections: an id among them seen again starts a new track, and the old
        track's pending predictions are never scored. The way to end a track: give the ids
        your tracker reports lost here, or with their frame (`step(..., lost=)`)."""
        ids = stream_checks.as_array(ids, "forget: track ids").reshape(-1)
        if len(ids) and not np.issubdtype(ids.dtype, np.integer):
            raise DataError(f"forget: track ids must be integers, got {ids[:5].tolist()}")
        self._slots.lost.update(int(i) for i in ids)
        self._clock.forget(ids)

    def warm_up(self, max_people: int, max_compile_s: float | None = WARM_UP_COMPILE_S
                ) -> tuple[int, ...]:
        """Compile the step of every capacity this stream can grow to while it holds at most
        `max_people` tracks (those in view and those unseen for fewer than obs_len steps), so
        that no step compiles later; returns the capacities. Each is one program: with
        CrowdNav++'s predictor and DtACI regions, 15-17 s for the six up to 64 on a quiet 2-core
        CPU, 3.2-3.3 s from a warm `compilation_cache` (the programs read, each step traced)
        (docs/robot.md). The largest compiles first: a crowd whose step the memory cannot hold
        is refused in one line with XLA's estimate, and so is one whose compiles would take
        longer than `max_compile_s` in all (None: no bound), with the expected seconds. The
        stream's own state is left as it was."""
        if not (isinstance(max_people, numbers.Integral) and max_people >= 0):
            raise DataError(f"warm_up: max_people must be a whole number, got {max_people!r}")
        if max_compile_s is not None and not (isinstance(max_compile_s, numbers.Real)
                                              and max_compile_s > 0):
            raise DataError(f"warm_up: max_compile_s must be seconds above 0 (or None: no "
                            f"bound), got {max_compile_s!r}")
        return self._slots.warm_up(bucket_size(max_people + (1 if self.robot else 0)),
                                   max_compile_s)

    # --- Saved and restored: a restarted robot's warm tracks and discs ---------------------

    # What a saved stream keeps of the host beside its state: each field's name in the file,
    # the attribute that holds it (the stream's, or its slots' `_slots.NAME`) and how the file
    # holds it (`gst_jax.stream_file`). An attribute the host adds that outlives a step is one
    # more line here.
    _KEPT = {
        "frames": ("_slots.frames", stream_file.COUNT),
        "restarts": ("restarts", stream_file.COUNT),
        "_lost": ("_slots.lost", stream_file.TRACK_IDS),
        "_clock": ("_clock", stream_file.Kept(Clock.as_json, Clock.from_json)),
        "key": ("_slots.key", stream_file.KEY),
        "_floor": ("_slots._floor", stream_file.COUNT),
        "_small_frames": ("_slots._small_frames", stream_file.COUNT),
        "_small_peak": ("_slots._small_peak", stream_file.COUNT),
        "fallbacks": ("_slots.fallbacks", stream_file.COUNT),
        "overruns": ("_slots._programs.overruns", stream_file.COUNT),
    }

    def save(self, path: str | Path) -> Path:
        """Write the tracks (their histories, score buffer, conformal and adaptation states)
        and the host's fields (`_KEPT`: frames, clock, key, ...) to one safetensors file,
        atomically (written beside it, then renamed: a crash leaves the last save whole);
        returns its path. `load` resumes from it."""
        host = {name: kept.write(operator.attrgetter(attribute)(self))
                for name, (attribute, kept) in self._KEPT.items()}
        return stream_file.write(path, jax.tree.map(np.asarray, self.state), self._identity(),
                                 host)

    def load(self, path: str | Path) -> Stream:
        """This stream, holding what `save` wrote to `path`: from now on it steps as the saved
        stream would have, bit for bit (its key and frame count are the saved ones; `seed`
        no longer counts; its capacity is the saved one's). Built as the saved stream was (the
        same model and parameters, step, regions, adaptation and robot), or the file is
        refused in one line naming what differs (`DataError`), as a damaged file is
        (`gst_jax.stream_file`). max_speed, non_finite, compilation_cache and max_gap_s are
        this one's.

            stream = Stream(run, regions=Regions("dtaci", 0.1)).load("stream.safetensors")
        """
        state, host = stream_file.read(path, self._identity(), self._slots.empty_state,
                                       {name: kept for name, (_, kept) in self._KEPT.items()})
        self.state = state
        for name, value in host.items():
            owner, _, attribute = self._KEPT[name][0].rpartition(".")
            setattr(operator.attrgetter(owner)(self) if owner else self, attribute, value)
        return self

    def _identity(self) -> dict:
        """What this stream's tracks are of: a file of another's is refused on loading."""
        return {"predictor": repr(self.model),
                "params_sha256": stream_file.params_digest(self.params),
                "step_s": self.grid.step_s, "regions": repr(self.regions),
                "adaptation": repr(self.adaptation), "robot": self.robot}


if __name__ == "__main__":      # python -m gst_jax.stream replay ...: the stream's commands
    from gst_jax.stream_commands import main

    main()
