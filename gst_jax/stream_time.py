"""A tracker's frames, at its own times, as the model's steps (numpy only): what `Stream.step`
does with a frame's `time`.

The model steps on a fixed grid, `step_s` apart; a tracker reports when it likes (5 Hz, 10 Hz,
15 Hz, jittered, frames dropped). The `Clock` lays an absolute grid of ticks from the first
frame's time, tick k at origin + k step_s, and reaches a tick once a frame at or after it
arrives (at most one tick of latency): a frame reaches every tick since the last frame up to
its own time, none, one or several.

    clock = Clock(step_s=0.25)
    reached = clock.frame(time, ids, positions, gate)     # Reached: ticks, fills, restarted

At a tick, each track's position is interpolated linearly from its raw detections on both
sides of it, at most MAX_INTERPOLATED_STEPS steps apart (farther apart, it counts as not
detected at the ticks between); a detection at the tick itself (within TICK_S) is taken as it
is. So:

- A track absent from the frame that reaches a tick (its detection missed, the person hidden)
  is not detected at that tick when it is reached; seen again within the limit, the ticks it
  missed are filled in afterwards (`Reached.fills`: the host writes them into the histories,
  so that it is predicted again from its next tick on).
- A track's first tick is the first at or after its first detection that has a detection on
  each side: a track seen first between two ticks is detected from the next.
- A frame that reaches no tick changes no prediction (the host repeats the last tick's); its
  detections wait for the next tick.
- A frame before or at the last frame's time is refused in one line (`DataError`), as is a
  time that cannot be seconds (beyond MAX_TIME_S: a Unix time in milliseconds). The host
  refuses a frame too far after the last (`Stream(max_gap_s=)`), before the clock moves.

Each known id's raw detection is judged by the stream's `Gate` (`gst_jax.stream_core`) from
its last two raw detections before it is interpolated from: another person's
(`Reached.restarted`) is never interpolated towards, and its track starts afresh (the host
ends the old one at the next tick, as `Stream.forget` does).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import numbers
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from gst_jax.config import MAX_STEP_S, MIN_STEP_S
from gst_jax.data.readers import MAX_INTERPOLATED_STEPS
from gst_jax.errors import DataError

if TYPE_CHECKING:
    from gst_jax.stream_core import Gate

logger = logging.getLogger("gst_jax.stream")

# MAX_INTERPOLATED_STEPS (the data readers' rule, the same for a stream): two raw detections
# of a track at most this many model steps apart are interpolated between: a tracker at half
# the model's rate, or one that missed a few frames at a higher one. Over a longer gap a
# straight line would invent the path the model is to predict.
# A detection this close to a tick (seconds) is at the tick: timestamps' float rounding.
TICK_S = 1e-6
# A frame's time is seconds from any origin, but not beyond this: 1e10 s is over 300 years of
# Unix time, where a Unix time in milliseconds is 1.7e12 (and float64 still resolves TICK_S).
MAX_TIME_S = 1e10
# The longest gap a stream may be told to accept (`Stream(max_gap_s=)`), in model steps: the
# clock reaches each of a gap's steps in turn (2**16: 4.5 hours at 0.25 s).
MAX_GAP_STEPS = 2**16
# The most ticks a clock counts: the width of the step counter they feed (int32, the key's).
MAX_TICKS = int(np.iinfo(np.int32).max)


class Tick(NamedTuple):
    """One tick reached: its number (the first frame's is 0), its time (s), and the
    tracks detected at it, ids (M,) int32 and positions (M, 2)."""

    number: int
    time: float
    ids: np.ndarray
    positions: np.ndarray


class Reached(NamedTuple):
    """What a frame brings: the ticks it reaches, oldest first; fills, earlier ticks' detections
    of tracks that were missing then and are seen again now (ids (F,), tick indices (F,),
    positions (F, 2)); restarted, the ids whose raw detection the gate judged another
    person's (sorted)."""

    ticks: list[Tick]
    fills: tuple[np.ndarray, np.ndarray, np.ndarray]
    restarted: np.ndarray


@dataclasses.dataclass
class Clock:
    """The resampler's state, plain values and the last output's arrays (a saved stream keeps
    them: `as_json`).

    step_s: the model's step (s). origin: the first frame's time, tick 0 (None before it).
    ticks: the ticks reached so far. last_time: the last frame's time. samples: per track id
    its last two raw detections, [[time, x, y] or None (none before), [time, x, y]], kept while
    the last is within MAX_INTERPOLATED_STEPS of the last frame. last_output: the host's
    output at the last tick, arrays by name (ids, futures, radii or None), which a frame that
    reaches no tick repeats.
    """

    step_s: float
    origin: float | None = None
    ticks: int = 0
    last_time: float | None = None
    samples: dict[int, list] = dataclasses.field(default_factory=dict)
    last_output: dict[str, Any] | None = None

    def tick_time(self, index: int) -> float:
        assert self.origin is not None, "a clock that has seen a frame"
        return self.origin + index * self.step_s

    def forget(self, ids) -> None:
        """End these tracks: their next detection is interpolated from nothing before it."""
        for track in ids:
            self.samples.pop(int(track), None)

    def frame(self, time, ids: np.ndarray, positions: np.ndarray, gate: Gate | None
              ) -> Reached:
        """A frame at `time` (s) of tracks `ids` (M,) at `positions` (M, 2): the ticks it
        reaches with every track's interpolated position, the fills and the restarted ids
        (`Reached`); the clock moves on. A time not after the last frame's is refused."""
        time = self.checked_time(time)
        if self.origin is None:
            self.origin = time
        reach_s = MAX_INTERPOLATED_STEPS * self.step_s
        ids = np.asarray(ids, np.int64)
        positions = np.asarray(positions, np.float64).reshape(len(ids), 2)
        if self.last_time is not None and time - self.last_time > reach_s:
            logger.info("a frame at %.3f s comes %.3f s (%.1f model steps) after the last: "
                        "nobody is interpolated across the gap, its empty steps run at once",
                        time, time - self.last_time, (time - self.last_time) / self.step_s)
        # Each id's last raw detection (before: where there is none, or another person's).
        before = np.full((len(ids), 3), np.nan)
        restarted = []
        for row, track in enumerate(ids.tolist()):
            kept = self.samples.get(track)
            if kept is None:
                continue
            earlier, last = kept
            if gate is not None and self._another_person(gate, earlier, last, positions[row],
                                                         time):
                restarted.append(track)
                continue
            if time - last[0] <= reach_s + TICK_S:
                before[row] = last
        first = self.ticks
        last_index = self._last_index(time)
        ticks = [self._tick(k, ids, positions, time, before)
                 for k in range(first, last_index + 1)]
        fills = self._fills(ids, positions, time, before, first)
        for row, track in enumerate(ids.tolist()):
            kept = self.samples.get(track)
            earlier = None if kept is None or track in restarted else kept[1]
            self.samples[track] = [earlier, [time, *positions[row].tolist()]]
        self.samples = {track: kept for track, kept in self.samples.items()
                        if time - kept[1][0] <= reach_s + TICK_S}
        self.ticks = max(first, last_index + 1)
        self.last_time = time
        return Reached(ticks, fills, np.array(sorted(restarted), np.int32))

    def _last_index(self, time: float) -> int:
        """The last tick at or before `time` (within TICK_S)."""
        assert self.origin is not None, "a clock that has seen a frame"
        return math.floor((time - self.origin) / self.step_s + TICK_S / self.step_s)

    def ticks_reached(self, time: float) -> int:
        """How many ticks a frame at `time` (checked) would reach."""
        if self.origin is None:
            return 1
        return max(0, self._last_index(time) + 1 - self.ticks)

    def checked_time(self, time) -> float:
        """`time` as seconds, or a one-line refusal: not a finite number, not seconds (beyond
        MAX_TIME_S), or not after the last frame's."""
        if not (isinstance(time, numbers.Real) and math.isfinite(time)):
            raise DataError(f"a frame's time must be a finite number of seconds, got {time!r}")
        time = float(time)
        if abs(time) > MAX_TIME_S:
            raise DataError(f"a frame's time must be seconds (from any origin, within "
                            f"{MAX_TIME_S:g} of 0), got {time:g}: a Unix time in milliseconds "
                            "or nanoseconds? Divide it by 1e3 or 1e9")
        if self.last_time is not None and time <= self.last_time:
            message = (f"a frame at time {time:g} s comes at or before the last one "
                       f"({self.last_time:g} s): frames must come in the order of their times")
            logger.error(message)
            raise DataError(message)
        return time

    @staticmethod
    def _another_person(gate: Gate, earlier, last, xy: np.ndarray, time: float) -> bool:
        """Whether the detection `xy` at `time` is another person's than the track whose last
        two raw detections are `earlier` (or None) and `last`, [time, x, y]."""
        last_xy = np.asarray(last[1:])
        velocity = np.zeros(2)
        if earlier is not None and last[0] > earlier[0]:
            velocity = (last_xy - np.asarray(earlier[1:])) / (last[0] - earlier[0])
        return bool(gate.another_person(last_xy, velocity, np.asarray(earlier is not None),
                                        xy, np.asarray(time - last[0])))

    def _tick(self, index: int, ids: np.ndarray, positions: np.ndarray, time: float,
              before: np.ndarray) -> Tick:
        """Tick `index` (at or before `time`, after the last frame): the tracks detected at
        it, interpolated between their raw detection `before` (M, 3) and this frame's."""
        at = self.tick_time(index)
        if time - at <= TICK_S:                           # the frame is at the tick
            return Tick(index, at, ids.astype(np.int32), positions)
        known = ~np.isnan(before[:, 0])
        share = (at - before[known, 0]) / (time - before[known, 0])         # (0, 1)
        xy = before[known, 1:] + share[:, None] * (positions[known] - before[known, 1:])
        return Tick(index, at, ids[known].astype(np.int32), xy)

    def _fills(self, ids: np.ndarray, positions: np.ndarray, time: float, before: np.ndarray,
               first: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ticks reached before this frame (index < first) but after a track's raw
        detection `before`: it was missing from the frames that reached them, now
        interpolated."""
        filled_ids, filled_ticks, filled_xy = [], [], []
        for row in np.flatnonzero(~np.isnan(before[:, 0])):
            since, xy = before[row, 0], before[row, 1:]
            start = math.floor((since - self.origin) / self.step_s + TICK_S / self.step_s) + 1
            for index in range(start, first):
                share = (self.tick_time(index) - since) / (time - since)
                filled_ids.append(ids[row])
                filled_ticks.append(index)
                filled_xy.append(xy + share * (positions[row] - xy))
        return (np.array(filled_ids, np.int32), np.array(filled_ticks, np.int64),
                np.array(filled_xy, np.float64).reshape(-1, 2))

    def as_json(self) -> dict:
        """The clock as JSON values, the last output's arrays as numpy arrays (a saved stream
        keeps each as a tensor: `gst_jax.stream_file.Kept`); `from_json` reads them back."""
        return {"step_s": self.step_s, "origin": self.origin, "ticks": self.ticks,
                "last_time": self.last_time,
                "samples": [[track, *kept] for track, kept in sorted(self.samples.items())],
                "last_output": None if self.last_output is None else {
                    name: None if array is None else np.asarray(array)
                    for name, array in self.last_output.items()}}

    @classmethod
    def from_json(cls, value) -> Clock:
        """A clock from `as_json`'s values, or a ValueError saying what they must be."""
        def seconds(x, none=True):
            if (x is None and none) or (isinstance(x, (int, float)) and not isinstance(x, bool)
                                        and math.isfinite(x) and abs(x) <= MAX_TIME_S):
                return x
            raise ValueError(f"must hold finite seconds, within {MAX_TIME_S:g} of 0")

        def sample(x, none=False):
            if x is None and none:
                return None
            if not (isinstance(x, list) and len(x) == 3):
                raise ValueError("must hold samples [time, x, y]")
            return [float(seconds(v, none=False)) for v in x]

        fields = {"step_s", "origin", "ticks", "last_time", "samples", "last_output"}
        if not (isinstance(value, dict) and set(value) == fields):
            raise ValueError(f"must be a clock: {', '.join(sorted(fields))}")
        ticks = value["ticks"]
        if type(ticks) is not int or not 0 <= ticks <= MAX_TICKS:
            raise ValueError(f"must count its ticks with a whole number from 0 to {MAX_TICKS}")
        samples = {}
        for entry in value["samples"] if isinstance(value["samples"], list) else [None]:
            if not (isinstance(entry, list) and len(entry) == 3 and type(entry[0]) is int
                    and entry[0] >= 0):
                raise ValueError("must hold samples [track id, earlier, last]")
            samples[entry[0]] = [sample(entry[1], none=True), sample(entry[2])]
        step_s = seconds(value["step_s"], none=False)
        if not MIN_STEP_S <= step_s <= MAX_STEP_S:
            raise ValueError(f"must have a step from {MIN_STEP_S:g} to {MAX_STEP_S:g} s")
        return cls(float(step_s), seconds(value["origin"]), ticks, seconds(value["last_time"]),
                   samples, _arrays(value["last_output"]))


class FrameGap(DataError):
    """A frame refused for coming more than max_gap_s after the last one (`Jumps`), with what
    a caller that skips it (a bag's replay) reports: its time, the gap and the bound (s)."""

    def __init__(self, message: str, time: float, gap_s: float, max_gap_s: float):
        super().__init__(message)
        self.time, self.gap_s, self.max_gap_s = time, gap_s, max_gap_s


@dataclasses.dataclass
class Jumps:
    """What `Stream` makes of a frame that comes more than `max_gap_s` after the last one: a
    stray timestamp, times in milliseconds, or a tracker that did pause so long. It is refused
    in one line, before anything moves; the next frame within max_gap_s after it confirms the
    jump, and the host starts the tracks afresh from that one.

    max_gap_s: the bound (s); horizon_s: obs_len + pred_len model steps (s), the default
    bound, named so in the refusal. jumped_to: the last frame refused so (its time), or None.
    """

    max_gap_s: float
    horizon_s: float
    jumped_to: float | None = None

    def confirmed(self, time: float, last_time: float | None, step_s: float) -> bool:
        """Whether a frame at `time` (checked, after `last_time`) confirms a jump refused
        before; False where it comes within max_gap_s of the last frame. A frame further on
        that confirms nothing is refused (`FrameGap`, a `DataError`), and kept for the next
        to confirm."""
        if last_time is None or time - last_time <= self.max_gap_s:
            self.jumped_to = None
            return False
        if self.jumped_to is not None and 0 < time - self.jumped_to <= self.max_gap_s:
            logger.info("a frame at %g s confirms the jump to %g s: the tracks start afresh",
                        time, self.jumped_to)
            self.jumped_to = None
            return True
        self.jumped_to = time
        gap = time - last_time
        bound = f"{self.max_gap_s:g} s" + (
            " (obs_len + pred_len model steps, beyond which nothing of the tracks is left)"
            if self.max_gap_s == self.horizon_s else "")
        message = (f"a frame at time {time:g} s comes {gap:.6g} s ({gap / step_s:.6g} model "
                   f"steps) after the last one ({last_time:g} s), more than max_gap_s {bound}: "
                   "refused, the stream unchanged. Times must be seconds (in milliseconds a "
                   "10 Hz tracker's frames come 100 apart); after a real pause, the next frame "
                   f"within {self.max_gap_s:g} s after this one starts the tracks afresh "
                   "(Stream(max_gap_s=...) allows longer gaps)")
        logger.error(message)
        raise FrameGap(message, time, gap, self.max_gap_s)


# How a clock's last output is read back: each array's dtype (ids, futures and radii).
_OUTPUT_DTYPES = {"ids": np.int32, "futures": np.float32, "radii": np.float32}


def _arrays(value) -> dict[str, np.ndarray | None] | None:
    """`Clock.as_json`'s last output, checked and copied, or a ValueError: ids (L,), futures
    (L, P, 2) or (L, K, P, 2), radii (L, P) or None."""
    if value is None:
        return None
    if not (isinstance(value, dict) and set(value) == set(_OUTPUT_DTYPES)):
        raise ValueError(f"must hold the last output's {', '.join(_OUTPUT_DTYPES)}")
    for name, dtype in _OUTPUT_DTYPES.items():
        array = value[name]
        if array is None and name == "radii":
            continue
        if not (isinstance(array, np.ndarray) and array.dtype == dtype):
            raise ValueError(f"must hold the last output's {name} as an array of "
                             f"{np.dtype(dtype)}")
        if np.isnan(array).any() or (name != "futures" and (array < 0).any()):
            raise ValueError(f"must hold a last output whose {name} are numbers (ids, radii: "
                             "0 or more)")
    ids, futures, radii = value["ids"], value["futures"], value["radii"]
    if not (ids.ndim == 1 and futures.ndim in (3, 4) and futures.shape[0] == len(ids)
            and futures.shape[-1] == 2
            and (radii is None or radii.shape == (len(ids), futures.shape[-2]))):
        raise ValueError("must hold a last output of ids (L,), futures (L, P, 2) or "
                         "(L, K, P, 2) and radii (L, P)")
    return {name: None if array is None else np.array(array) for name, array in value.items()}
