"""What a file's tracks, on the model's time grid and in metres, say about how it was read
(numpy only): walking speeds that betray a wrong `--units` or `--fps`, and the longest track,
which says why a file gives no window.

The speed thresholds come from the bundled scenes (median and 99th percentile speed over
consecutive detections of one person, at 0.4 s, m/s): eth 2.45 / 3.60, hotel 1.28 / 2.18,
univ 0.52 / 1.64 and 0.72 / 1.72, zara1 1.15 / 1.82, zara2 1.01 / 1.86, lcas 0.075 / 2.31
(most of its people stand), wildtrack 0.83 / 2.06 (its 2 Hz interpolated), data/samples
1.13 / 1.82, and the navigation task's simulated humans 0.73 / 1.09 and 0.89 / 1.60 (at 0.25 s).
A wrong unit is off by 3.3x (ft), 100x (cm) or 1000x (mm); a wrong rate by the ratio of rates.
Whichever of a unit and a common frame rate brings the speeds nearer a crowd's is named first.
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
# Frame rates of videos and trackers (frame ids per second) that a wrong or missing --fps may
# have meant.
COMMON_FPS = (2.5, 5.0, 10.0, 12.5, 15.0, 20.0, 25.0, 30.0, 50.0, 60.0)


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
                 frame_ids_per_s: float | None = None, own: bool = True,
                 frame_step: int = 1, fps_assumed: bool = False) -> None:
    """Refuse (`DataError`) a file whose people move at a median speed no pedestrian walks,
    and warn about one merely fast or slow, naming the likely mistake and the flag that
    fixes it. tracks: on the model's grid (`step_s` seconds a step), in metres; scale:
    metres per unit of the file; frame_ids_per_s: the rate its frame ids were read at; own:
    a `--data` file (the flags apply), not a bundled scene; frame_step: the file's frame ids
    per row; fps_assumed: no --fps and no rate in the file, so that its rows were taken to be
    the model's steps, which a tracker's frame ids counting every frame (frame_step 1) belie
    when another rate makes them walk (warned about)."""
    speeds = step_speeds(tracks, step_s)
    if not len(speeds):
        return
    median, fast = float(np.median(speeds)), float(np.percentile(speeds, 90))
    unit = next((name for name, metres in UNITS.items() if metres == scale), f"{scale:g} m")
    read = f"read in {unit}" + (f", frame ids at {frame_ids_per_s:g} per second"
                                if frame_ids_per_s else "")
    rates = _Rates(frame_ids_per_s, frame_step, 1 / step_s, fps_assumed)
    if median > ABSURD_SPEED:
        raise DataError(f"{tracks.path}: its people move at a median {median:.3g} m/s ({read}), "
                        f"which no pedestrian does; {_fix(median, fast, unit, scale, own, rates)}")
    if median > FAST_SPEED:
        warnings.warn(f"{tracks.path}: its people move at a median {median:.3g} m/s ({read}), "
                      f"fast for pedestrians; {_fix(median, fast, unit, scale, own, rates)}",
                      stacklevel=3)
    elif fast < SLOW_SPEED:
        warnings.warn(f"{tracks.path}: 90% of its steps are slower than {fast:.3g} m/s (median "
                      f"{median:.3g} m/s, {read}), slow for pedestrians; "
                      f"{_fix(median, fast, unit, scale, own, rates)}", stacklevel=3)
    elif own and fps_assumed and frame_step == 1 and median < TYPICAL_SPEED / 2:
        # Walking, slowly: a 10 Hz tracker's file read as 2.5 Hz walks at a quarter speed.
        better = [(distance, fps, speed) for distance, fps, speed in rates.candidates(median, fast)
                  if fast * fps / rates.fps <= FAST_SPEED and distance < _distance(median)]
        if better:
            _, fps, speed = min(better)
            warnings.warn(f"{tracks.path}: no --fps, so its rows are taken to be the model's "
                          f"steps, {step_s:g} s apart, where its people walk a median "
                          f"{median:.2g} m/s; its frame ids count every frame, as a video's or "
                          f"a tracker's do: at --fps {fps:g} they would walk {speed:.2g} m/s "
                          "(give --fps, the frame ids per second)", stacklevel=3)


def _walking(median: float, fast: float) -> bool:
    return median <= FAST_SPEED and fast >= SLOW_SPEED


def _distance(speed: float) -> float:
    """How far a median speed is from a crowd's typical one (a ratio: log)."""
    return abs(math.log(speed / TYPICAL_SPEED)) if speed else math.inf


class _Rates:
    """The frame rates a file's frame ids may have meant instead of the one they were read at:
    the common ones (COMMON_FPS) that give a rate the model's is a divisor of."""

    def __init__(self, fps: float | None, frame_step: int, model_hz: float, assumed: bool):
        # 0 where no rate was read: then there is no other rate either, nor a division by it.
        self.fps, self.assumed = fps or 0.0, assumed
        self.others = [] if not fps else [
            other for other in COMMON_FPS
            if not math.isclose(other, fps) and other / frame_step >= model_hz * (1 - 1e-6)
            and math.isclose(other / frame_step / model_hz,
                             round(other / frame_step / model_hz), abs_tol=1e-6)]

    def candidates(self, median: float, fast: float) -> list[tuple[float, float, float]]:
        """(distance from a typical speed, fps, median speed) of each rate that makes these
        speeds a crowd's."""
        return [(_distance(median * other / self.fps), other, median * other / self.fps)
                for other in self.others
                if _walking(median * other / self.fps, fast * other / self.fps)]


def _fix(median: float, fast: float, unit: str, scale: float, own: bool, rates: _Rates) -> str:
    """The flag that would make these speeds a crowd's: a unit or --fps, whichever brings them
    nearer a typical speed first."""
    if not own:
        return "the bundled scenes' files are read in metres, a row every 0.4 s"
    units = [(_distance(median * metres / scale), name, median * metres / scale)
             for name, metres in UNITS.items()
             if name != unit and _walking(median * metres / scale, fast * metres / scale)]
    verb = "add" if unit == "m" else "use"
    fps = rates.candidates(median, fast)
    if fps and (not units or min(fps) < min(units)):
        _, other, speed = min(fps)
        said = "give" if rates.assumed else "check"
        text = (f"at --fps {other:g} it would be {speed:.2g} m/s: {said} --fps (frame ids per "
                f"second: a wrong rate scales every speed)")
        if units:
            _, name, speed = min(units)
            text += f"; in {name} it would be {speed:.2g} m/s (--units {name})"
        return text
    if units:
        _, name, speed = min(units)
        return f"in {name} it would be {speed:.2g} m/s: {verb} --units {name}"
    return ("no --units makes that a walking speed: check the coordinates, and --fps (frame "
            "ids per second: a wrong rate scales every speed)")
