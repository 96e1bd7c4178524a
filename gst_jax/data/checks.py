"""What a file's tracks, on the model's time grid and in metres, say about how it was read
(numpy only): walking speeds that betray a wrong `--units` or `--fps`, and the longest track,
which says why a file gives no window.

The speed thresholds come from the bundled scenes (median and 99th percentile speed over
consecutive detections of one person, at 0.4 s, m/s): eth 2.45 / 3.60, hotel 1.28 / 2.18,
univ 0.52 / 1.64 and 0.72 / 1.72, zara1 1.15 / 1.82, zara2 1.01 / 1.86, lcas 0.075 / 2.31
(most of its people stand), wildtrack 1.03 / 2.80, data/samples 1.13 / 1.82 and 0.66 / 1.44.
A wrong unit is off by 3.3x (ft), 100x (cm) or 1000x (mm); a wrong rate by the ratio of rates.
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from gst_jax.data.readers import UNITS, Tracks
from gst_jax.errors import DataError

# A median above ABSURD_SPEED (m/s) is refused: 4x eth's, the fastest bundled scene, and what
# data in cm or mm read as metres give (100x, 1000x).
ABSURD_SPEED = 10.0
# A median above FAST_SPEED (m/s) is warned about: 1.6x eth's; a brisk crowd in feet read as
# metres (3.3x).
FAST_SPEED = 4.0
# The 90th percentile, not the median, decides "too slow": most of lcas's people stand (median
# 0.075 m/s), but in every bundled scene the fastest tenth of steps walk (>= 1.14 m/s), 4.5x
# SLOW_SPEED. Data 10x too slow (a 25 Hz tracker's frame ids read without --fps) fall below.
SLOW_SPEED = 0.25
# The speed a suggested unit should bring the median nearest to (the bundled scenes' typical).
TYPICAL_SPEED = 1.2


def step_speeds(tracks: Tracks, step_s: float) -> np.ndarray:
    """(K,) m/s over every pair of consecutive detections of one pedestrian, `tracks` on a
    grid whose `frame_step` is `step_s` seconds."""
    order = np.lexsort((tracks.frames, tracks.pedestrians))
    frames, pedestrians, xy = (tracks.frames[order], tracks.pedestrians[order],
                               tracks.xy[order])
    consecutive = ((pedestrians[1:] == pedestrians[:-1])
                   & (np.diff(frames) == tracks.frame_step))
    return np.linalg.norm(np.diff(xy, axis=0)[consecutive], axis=1) / step_s


def longest_track(tracks: Tracks) -> int:
    """The most consecutive steps (on the file's grid) at which one pedestrian is detected."""
    order = np.lexsort((tracks.frames, tracks.pedestrians))
    frames, pedestrians = tracks.frames[order], tracks.pedestrians[order]
    if not len(frames):
        return 0
    breaks = ((pedestrians[1:] != pedestrians[:-1])
              | (np.diff(frames) != tracks.frame_step))
    starts = np.flatnonzero(np.concatenate([[True], breaks, [True]]))
    return int(np.diff(starts).max())


def check_speeds(tracks: Tracks, step_s: float, *, scale: float = 1.0,
                 frame_ids_per_s: float | None = None, own: bool = True) -> None:
    """Refuse (`DataError`) a file whose people move at a median speed no pedestrian walks,
    and warn about one merely fast or slow, naming the likely mistake and the flag that
    fixes it. tracks: on the model's grid (`step_s` seconds a step), in metres; scale:
    metres per unit of the file; frame_ids_per_s: the rate its frame ids were read at; own:
    a `--data` file (the flags apply), not a bundled scene."""
    speeds = step_speeds(tracks, step_s)
    if not len(speeds):
        return
    median, fast = float(np.median(speeds)), float(np.percentile(speeds, 90))
    unit = next((name for name, metres in UNITS.items() if metres == scale), f"{scale:g} m")
    read = f"read in {unit}" + (f", frame ids at {frame_ids_per_s:g} per second"
                                if frame_ids_per_s else "")
    if median > ABSURD_SPEED:
        raise DataError(f"{tracks.path}: its people move at a median {median:.3g} m/s ({read}), "
                        f"which no pedestrian does; {_fix(median, fast, unit, scale, own)}")
    if median > FAST_SPEED:
        warnings.warn(f"{tracks.path}: its people move at a median {median:.3g} m/s ({read}), "
                      f"fast for pedestrians; {_fix(median, fast, unit, scale, own)}",
                      stacklevel=3)
    elif fast < SLOW_SPEED:
        warnings.warn(f"{tracks.path}: 90% of its steps are slower than {fast:.3g} m/s (median "
                      f"{median:.3g} m/s, {read}), slow for pedestrians; "
                      f"{_fix(median, fast, unit, scale, own)}", stacklevel=3)


def _walking(median: float, fast: float) -> bool:
    return median <= FAST_SPEED and fast >= SLOW_SPEED


def _fix(median: float, fast: float, unit: str, scale: float, own: bool) -> str:
    """The flag that would make these speeds a crowd's: a unit if one does, else --fps."""
    if not own:
        return "the bundled scenes' files are read in metres, a row every 0.4 s"
    candidates = [(abs(math.log(median * metres / scale / TYPICAL_SPEED)) if median else 0.0,
                   name, median * metres / scale)
                  for name, metres in UNITS.items()
                  if name != unit and _walking(median * metres / scale, fast * metres / scale)]
    if candidates:
        _, name, speed = min(candidates)
        verb = "add" if unit == "m" else "use"
        return f"in {name} it would be {speed:.2g} m/s: {verb} --units {name}"
    return ("no --units makes that a walking speed: check the coordinates, and --fps (frame "
            "ids per second: a wrong rate scales every speed)")
