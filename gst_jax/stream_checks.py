"""A stream's inputs checked, each refused in one line (`DataError`) that says what was wrong
and the fix: a frame's ids and positions (`checked_frame`), the robot's position
(`with_robot`), and `gst_jax.stream.Stream`'s settings (`predictor`, `checked_gate`,
`check_timing`)."""

from __future__ import annotations

import math
import numbers

import numpy as np

from gst_jax.config import TimeGrid, check as check_config, rules
from gst_jax.data.batching import LARGEST_COORDINATE
from gst_jax.errors import DataError
from gst_jax.model import Params
from gst_jax.predictors import ConstantVelocity, Standing
from gst_jax.stream_core import Gate, StreamModel
from gst_jax.stream_time import MAX_GAP_STEPS

# The robot's id among the tracks: no tracker's.
ROBOT = np.iinfo(np.int32).max


def as_array(value, what: str) -> np.ndarray:
    """`value` as a numpy array, or a one-line refusal of a ragged one (lists of unequal
    lengths) or of what is no array at all."""
    try:
        return np.asarray(value)
    except (ValueError, TypeError) as error:
        raise DataError(f"{what} must be an array, got {type(value).__name__} "
                        f"{str(value)[:60]}: {str(error).split('.')[0]}") from None


def checked_frame(ids, positions, non_finite: str = "raise") -> tuple[np.ndarray, np.ndarray]:
    """A frame's ids (M,) and positions (M, 2), or a one-line refusal; with non_finite
    "undetected", the people whose position is not finite left out."""
    ids = as_array(ids, "a frame's ids")
    positions = as_array(positions, "a frame's positions")
    if ids.ndim != 1:
        raise DataError(f"a frame's ids must be (M,), got shape {ids.shape}")
    if positions.shape != (len(ids), 2) and not (len(ids) == 0 and positions.size == 0):
        raise DataError(f"a frame of {len(ids)} ids needs positions ({len(ids)}, 2): one "
                        f"(x, y) row per id; got shape {positions.shape}")
    if not np.issubdtype(positions.dtype, np.number):
        raise DataError(f"a frame's positions must be numbers, got {positions.dtype}")
    positions = positions.astype(np.float64).reshape(len(ids), 2)
    if len(ids) and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0
                     or ids.max() >= ROBOT):
        raise DataError(f"track ids must be integers from 0 to {ROBOT - 1}, got "
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


def with_robot(ids: np.ndarray, positions: np.ndarray, robot_xy
               ) -> tuple[np.ndarray, np.ndarray]:
    """A checked frame with the robot (`ROBOT`) at `robot_xy` as one more agent, or a
    one-line refusal of `robot_xy`."""
    if robot_xy is None:
        raise DataError("this stream has the robot as an agent: give robot_xy")
    robot_xy = np.asarray(robot_xy, np.float64)
    if robot_xy.shape not in ((2,), (1, 2)) or not np.isfinite(robot_xy).all() or (
            np.abs(robot_xy).max() > LARGEST_COORDINATE):
        raise DataError(f"robot_xy must be one finite position (2,) within "
                        f"{LARGEST_COORDINATE:.0e} m, got {robot_xy.tolist()}")
    return (np.append(ids, ROBOT).astype(np.int32),
            np.vstack([positions, robot_xy.reshape(1, 2)]))


def checked_gate(max_speed, max_acceleration, jump_tolerance) -> Gate | None:
    """`Stream`'s gate (`Gate`; None without max_speed), or a one-line refusal of one of its
    numbers."""
    speed = _gate_limit("max_speed", max_speed, "a positive number of m/s (or None)")
    acceleration = _gate_limit("max_acceleration", max_acceleration,
                               "a positive number of m/s^2 (or None)")
    tolerance = _gate_limit("jump_tolerance", jump_tolerance, "a number of metres, 0 or more",
                            0.0)
    return None if speed is None else Gate(speed, acceleration, tolerance or 0.0)


def _gate_limit(name: str, value, must_be: str, least: float | None = None) -> float | None:
    """One of the gate's numbers (`Stream`'s max_speed, ...) as a float (None stays None where
    `least` is None), or a one-line refusal: finite and above 0, or at least `least`."""
    if value is None and least is None:
        return None
    number = float(value) if isinstance(value, numbers.Real) else math.nan
    if not (math.isfinite(number) and (number > 0 if least is None else number >= least)):
        raise DataError(f"Stream: {name} must be {must_be}, got {value!r}")
    return number


def check_timing(deadline_s: float | str | None, shrink_after: int | None) -> None:
    """Refuse, in one line, a `Stream`'s deadline_s or shrink_after that is neither a number
    of its kind nor one of its words."""
    if deadline_s != "step" and deadline_s is not None and not (
            isinstance(deadline_s, numbers.Real) and 0 < deadline_s < math.inf):
        raise DataError(f"Stream: deadline_s must be a positive number of seconds, \"step\" "
                        f"(the model's step_s) or None (wait), got {deadline_s!r}")
    if shrink_after is not None and not (isinstance(shrink_after, numbers.Integral)
                                         and shrink_after >= 1):
        raise DataError(f"Stream: shrink_after must be a number of frames, 1 or more (or "
                        f"None: never shrink), got {shrink_after!r}")


def checked_max_gap(max_gap_s, grid: TimeGrid) -> float:
    """A `Stream`'s max_gap_s in seconds: "horizon" is obs_len + pred_len model steps (beyond
    them nothing of the tracks is left to predict or score); a number from one model step to
    MAX_GAP_STEPS of them; anything else refused in one line."""
    horizon = (grid.obs_len + grid.pred_len) * grid.step_s
    if isinstance(max_gap_s, str) and max_gap_s == "horizon":
        return horizon
    if (isinstance(max_gap_s, numbers.Real) and not isinstance(max_gap_s, bool)
            and grid.step_s <= float(max_gap_s) <= MAX_GAP_STEPS * grid.step_s):
        return float(max_gap_s)
    raise DataError(f"Stream: max_gap_s must be \"horizon\" (obs_len + pred_len model steps, "
                    f"{horizon:g} s) or seconds from one model step ({grid.step_s:g}) to "
                    f"{MAX_GAP_STEPS} of them ({MAX_GAP_STEPS * grid.step_s:g}), got "
                    f"{max_gap_s!r}")


def predictor(run, num_samples: int, mean: bool, convention: str, step_s
              ) -> tuple[StreamModel | ConstantVelocity | Standing, Params | None, bool,
                         TimeGrid]:
    """What `Stream` predicts with, from its run, num_samples, mean, convention and step_s:
    (the predictor, its parameters, mean, its time grid), or a one-line refusal of a setting
    that is not its kind's (a model's num_samples for a predictor without one, ...)."""
    if isinstance(run, (ConstantVelocity, Standing)):
        if (num_samples, mean, convention) != (1, True, "gst"):
            raise DataError(f"Stream: num_samples, mean and convention are a model's; "
                            f"{type(run).__name__} predicts one future per track")
        return run, None, True, predictor_grid(run, step_s)
    if not hasattr(run, "model_config"):
        raise DataError(f"Stream: run must be a loaded model (gst_jax.runs.load_model, e.g. "
                        f"load_model(\"pretrained:crowd_d\")), ConstantVelocity or Standing; "
                        f"got {type(run).__name__} {str(run)[:60]!r}")
    if step_s is not None:
        raise DataError("Stream: a model steps at its own step_s (its config's); "
                        "give step_s only with a predictor without a model")
    return (StreamModel(run.model_config, num_samples, mean, convention), run.params, mean,
            run.model_config.grid)


def predictor_grid(predictor: ConstantVelocity | Standing, step_s) -> TimeGrid:
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
