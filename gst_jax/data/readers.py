"""Readers of raw trajectory files into validated `Tracks` (numpy only).

Every problem with an input file is reported as a `DataError` naming the file, the line and
what is wrong, before any array is built: a bad file never turns into a silently wrong window.

One job, though over 400 lines: a file's rows to tracks at the model's rate, its formats (text
with or without a header, TrajNet++ ndjson) and its rate (every k-th row, or interpolated)
read by the same checks, so that every format is refused for the same faults in the same words.
"""

from __future__ import annotations

import csv
import dataclasses
import fractions
import json
import math
import warnings
from pathlib import Path
from typing import Iterator

import numpy as np

from gst_jax.errors import DataError

__all__ = ["Tracks", "interpolate_to_steps", "parse_columns", "read_text_tracks", "read_tracks",
           "read_trajnet_ndjson", "to_model_rate"]

# Frame and pedestrian ids are parsed as floats: beyond 2^53 they are no longer exact.
LARGEST_ID = 2 ** 53
# Metres per unit of a file's coordinates (--units).
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "ft": 0.3048}
# What a text file's columns hold, in the order `--columns` names them.
ROLES = ("frame", "pedestrian id", "x", "y")
# A file's rows at most this many model steps apart are interpolated between when its rate
# is not a multiple of the model's (`interpolate_to_steps`), as `Stream.step(..., time=)` does
# a tracker's frames (gst_jax.stream_time): farther apart, a straight line would invent the
# path the model is to predict.
MAX_INTERPOLATED_STEPS = 2
# Header names recognised without --columns (compared in lower case), per role.
HEADER_NAMES = {"frame": ("frame", "frame_id"),
                "pedestrian id": ("id", "ped", "ped_id", "pedestrian", "pedestrian_id",
                                  "track", "track_id"),
                "x": ("x",), "y": ("y",)}


@dataclasses.dataclass(frozen=True)
class Tracks:
    """All annotated rows of one file, sorted by (frame, pedestrian).

    Attributes:
      path: the file the rows came from.
      frames: (R,) int64 frame ids.
      pedestrians: (R,) int64 pedestrian ids.
      xy: (R, 2) float64 positions in metres.
      frame_step: frame-id difference between consecutive annotation steps: the most
        common difference between a pedestrian's consecutive frames. Every row lies on the
        file's grid of that step (rows off it are an error, or dropped on request).
      rate_hz: annotations per second stated by the file (a TrajNet++ scene's "fps"), or None.
    """

    path: str
    frames: np.ndarray
    pedestrians: np.ndarray
    xy: np.ndarray
    frame_step: int
    rate_hz: float | None = None


def read_tracks(path: str | Path, *, drop_off_grid: bool = False,
                columns: str | None = None) -> Tracks:
    """Read a text file (`frame ped x y` as the raw ETH/UCY files, or a tracker's CSV) or a
    TrajNet++ file (`.ndjson`).

    drop_off_grid: drop rows whose frame is off the file's grid (with a warning that counts
    them) instead of refusing the file.
    columns: which columns of a text file hold frame, pedestrian id, x and y (`--columns`,
    see `read_text_tracks`).
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    if path.suffix == ".ndjson":
        if columns:
            raise DataError(f"{path}: --columns {columns} names the columns of text files; a "
                            "TrajNet++ file's are its keys f, p, x, y")
        return read_trajnet_ndjson(path, drop_off_grid=drop_off_grid)
    return read_text_tracks(path, drop_off_grid=drop_off_grid, columns=columns)


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, text) of the non-blank lines; bytes that are not UTF-8 are an error."""
    for line_number, raw in enumerate(path.read_bytes().splitlines(), start=1):
        try:
            line = raw.decode("utf-8")
        except UnicodeDecodeError as error:
            raise DataError(f"{path}:{line_number}: not UTF-8 text (byte "
                            f"0x{raw[error.start]:02x} at column {error.start + 1})") from None
        if line.strip():
            yield line_number, line


def read_text_tracks(path: str | Path, *, drop_off_grid: bool = False,
                     columns: str | None = None) -> Tracks:
    """Rows of frame, pedestrian id, x, y in a text file: comma-separated (a tracker's CSV)
    or tab- or space-separated (the ETH/UCY raw files), with an optional header line (a
    first line in which no field is a number).

    columns: `--columns`, four comma-separated columns holding frame, pedestrian id, x and y,
    each a header name or a column number counted from 1 (MOTChallenge rows
    `frame,id,bb_left,bb_top,bb_width,bb_height,conf,x,y,z`: "1,2,8,9"). None: a header's
    recognised names (HEADER_NAMES), else exactly four columns `frame ped x y`.
    """
    path = Path(path)
    lines = _lines(path)
    first = next(lines, None)
    if first is None:
        return _build_tracks(path, [], drop_off_grid)
    split = _comma_fields if "," in first[1] else str.split
    first_fields = split(first[1])
    header: list[str] | None = first_fields
    if any(_is_number(field) for field in first_fields):
        header, lines = None, _chain(first, lines)
    where = _column_indices(path, first[0], header, parse_columns(columns) if columns else None)
    bare = header is None and not columns       # the ETH/UCY format: exactly frame ped x y
    width = len(split(first[1]))
    if max(where) >= width and columns:
        raise DataError(f"{path}:{first[0]}: --columns {columns} names column {max(where) + 1}, "
                        f"but the line has {width}: {first[1].strip()!r}")
    if max(where) >= width:
        raise DataError(f"{path}:{first[0]}: expected 4 columns (frame ped x y), found {width}: "
                        f"{first[1].strip()!r}; every row needs a frame, a pedestrian id, x and "
                        "y (a file with more columns names these four with --columns, e.g. "
                        "--columns 1,2,8,9)")
    rows = []
    for line_number, line in lines:
        fields = split(line)
        if bare and len(fields) != 4:
            raise DataError(f"{path}:{line_number}: expected 4 columns (frame ped x y), found "
                            f"{len(fields)}: {line.strip()!r}; a file with other columns names "
                            "them with --columns (e.g. --columns 1,2,8,9)")
        # Every row as wide as the first: a decimal comma in a CSV shifts the columns.
        if len(fields) != width:
            raise DataError(f"{path}:{line_number}: expected {width} columns as line "
                            f"{first[0]} has ({_describe(where)}), found {len(fields)}: "
                            f"{line.strip()!r}")
        rows.append(_parse_row(path, line_number, [fields[i] for i in where]))
    return _build_tracks(path, rows, drop_off_grid)


def parse_columns(spec: str) -> tuple[int | str, ...]:
    """`--columns` -> the four columns of frame, pedestrian id, x, y: 0-based indices for the
    numbers (counted from 1 in the flag), lower-case header names for the rest."""
    items = [item.strip() for item in spec.split(",")]
    if len(items) != 4 or not all(items):
        raise DataError(f"--columns {spec}: expected 4 comma-separated columns holding frame, "
                        "pedestrian id, x, y (header names or numbers from 1, e.g. "
                        "frame,id,x,y or 1,2,8,9)")
    parsed: list[int | str] = []
    for item in items:
        if item.isdigit():
            if int(item) < 1:
                raise DataError(f"--columns {spec}: columns are numbered from 1, got {item}")
            parsed.append(int(item) - 1)
        else:
            parsed.append(item.lower())
    if len(set(parsed)) < 4:
        raise DataError(f"--columns {spec}: names a column twice")
    return tuple(parsed)


def _column_indices(path: Path, line_number: int, header: list[str] | None,
                    columns: tuple[int | str, ...] | None) -> tuple[int, ...]:
    """The 0-based columns of frame, pedestrian id, x, y."""
    names = [name.strip().lower() for name in header] if header is not None else None
    shown = ", ".join(header) if header is not None else ""          # for the messages
    if columns is None:
        if names is None:
            return (0, 1, 2, 3)
        named = []
        for role in ROLES:
            found = [name for name in HEADER_NAMES[role] if name in names]
            if not found:
                *others, last = HEADER_NAMES[role]
                listed = f"{', '.join(others)} or {last}" if others else last
                raise DataError(f"{path}:{line_number}: the header ({shown}) names no "
                                f"{role} column: none of its columns is named {listed}; say "
                                "which columns hold frame, id, x, y with --columns (e.g. "
                                "--columns frame,id,x,y or 1,2,8,9)")
            named.append(found[0])
        columns = tuple(named)
    indices = []
    for column in columns:
        if isinstance(column, int):
            indices.append(column)
        elif names is None:
            raise DataError(f"{path}:{line_number}: --columns names the column {column!r}, but "
                            "the file has no header line (its first line holds numbers); "
                            "number the columns from 1 instead")
        elif column not in names:
            raise DataError(f"{path}:{line_number}: the header ({shown}) has no "
                            f"column {column!r}")
        else:
            indices.append(names.index(column))
    return tuple(indices)


def _describe(where: tuple[int, ...]) -> str:
    """'frame 1, pedestrian id 2, x 8, y 9': which column holds what, counted from 1."""
    return ", ".join(f"{role} {index + 1}" for role, index in zip(ROLES, where))


def _comma_fields(line: str) -> list[str]:
    return [field.strip() for field in next(csv.reader([line]))]


def _is_number(field: str) -> bool:
    try:
        float(field)
    except ValueError:
        return False
    return True


def _chain(first: tuple[int, str], rest: Iterator[tuple[int, str]]
           ) -> Iterator[tuple[int, str]]:
    yield first
    yield from rest


def read_trajnet_ndjson(path: str | Path, *, drop_off_grid: bool = False) -> Tracks:
    """TrajNet++ ndjson: `{"track": {"f", "p", "x", "y"}}` rows; `{"scene": ...}` rows skipped."""
    path = Path(path)
    rows, rates = [], set()
    for line_number, line in _lines(path):
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            raise DataError(f"{path}:{line_number}: not valid JSON ({error.msg})") from None
        except RecursionError:       # json's decoder recurses once per bracket
            raise DataError(f"{path}:{line_number}: not valid JSON (nested too deeply)") from None
        if not isinstance(record, dict) or not ({"scene", "track"} & record.keys()):
            raise DataError(f"{path}:{line_number}: expected a 'scene' or 'track' record")
        if "scene" in record:
            if isinstance(record["scene"], dict) and "fps" in record["scene"]:
                rates.add(record["scene"]["fps"])
            continue
        track = record["track"]
        if not isinstance(track, dict):
            raise DataError(f"{path}:{line_number}: 'track' is not an object: {track!r}")
        missing = [k for k in ("f", "p", "x", "y") if k not in track]
        if missing:
            raise DataError(f"{path}:{line_number}: track record lacks {', '.join(missing)}")
        for key, name in zip("fpxy", ("frame", "pedestrian id", "x", "y")):
            value = track[key]     # JSON numbers only: not true/false, not "1.5"
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise DataError(f"{path}:{line_number}: {name} is not a number: {value!r}")
        rows.append(_parse_row(path, line_number, [track[k] for k in ("f", "p", "x", "y")]))
    tracks = _build_tracks(path, rows, drop_off_grid)
    if len(rates) > 1:
        raise DataError(f"{path}: its scenes state several rates ({sorted(rates)} fps)")
    return dataclasses.replace(tracks, rate_hz=float(rates.pop()) if rates else None)


def _parse_row(path: Path, line_number: int, fields: list) -> tuple[int, int, float, float, int]:
    values = []
    for name, field in zip(ROLES, fields):
        try:
            value = float(field)
        except (TypeError, ValueError):
            raise DataError(f"{path}:{line_number}: {name} is not a number: {field!r}") from None
        if not math.isfinite(value):
            raise DataError(f"{path}:{line_number}: {name} is not finite: {field!r}")
        values.append(value)
    frame, pedestrian, x, y = values
    for name, value in (("frame", frame), ("pedestrian id", pedestrian)):
        if abs(value) >= LARGEST_ID:
            raise DataError(f"{path}:{line_number}: {name} {value:.6g} is too large to be an "
                            f"exact integer (the largest is 2^53)")
        if value != int(value):
            raise DataError(f"{path}:{line_number}: {name} is not an integer: {value!r}")
    return int(frame), int(pedestrian), x, y, line_number


def _build_tracks(path: Path, rows: list, drop_off_grid: bool = False) -> Tracks:
    if not rows:
        raise DataError(f"{path}: empty file (no trajectory rows)")
    seen: dict[tuple[int, int], int] = {}
    for frame, pedestrian, _, _, line_number in rows:
        first = seen.setdefault((frame, pedestrian), line_number)
        if first != line_number:
            raise DataError(f"{path}:{line_number}: duplicate row for frame {frame}, pedestrian "
                            f"{pedestrian} (first at line {first})")
    frames = np.array([row[0] for row in rows], dtype=np.int64)
    pedestrians = np.array([row[1] for row in rows], dtype=np.int64)
    xy = np.array([row[2:4] for row in rows], dtype=np.float64)
    lines = np.array([row[4] for row in rows])
    frame_step, phase = _frame_grid(frames, pedestrians)
    off_grid = (frames - phase) % frame_step != 0
    if off_grid.any():
        first = int(np.argmax(off_grid))
        count = int(off_grid.sum())
        if not drop_off_grid:
            raise DataError(
                f"{path}:{lines[first]}: frame {frames[first]} is off the file's grid (every "
                f"{frame_step} frames from {phase}); {count} row(s) are off it (drop them with "
                "--drop-off-grid)")
        warnings.warn(f"{path}: dropped {count} row(s) off the grid of every {frame_step} "
                      f"frames from {phase} (first at line {lines[first]})", stacklevel=2)
        frames, pedestrians, xy = frames[~off_grid], pedestrians[~off_grid], xy[~off_grid]
    order = np.lexsort((pedestrians, frames))
    return Tracks(path=str(path), frames=frames[order], pedestrians=pedestrians[order],
                  xy=xy[order], frame_step=frame_step)


def to_model_rate(tracks: Tracks, fps: float | None, model_hz: float, scale: float = 1.0, *,
                  own: bool = True) -> Tracks:
    """Tracks at the model's rate and in metres. fps: frame ids per second (None: the file's
    stated rate, else annotations taken to be at the model's rate); scale: metres per unit;
    own: a `--data` file (the refusals name its flags), not a bundled scene.

    Annotated at k times `model_hz` (k a whole number): every k-th annotation is kept, from
    the file's first frame, the rows themselves. At any other rate down to half `model_hz`
    (rows at most 2 steps apart, MAX_INTERPOLATED_STEPS): each track interpolated to the
    model's steps (`interpolate_to_steps`), if a step is a whole number of frame ids. Slower
    data, or steps that fall between frame ids, are refused in one line.
    """
    if fps is None:
        rate = tracks.rate_hz or model_hz
        fps = rate * tracks.frame_step
    rate = fps / tracks.frame_step
    keep_every = rate / model_hz
    if keep_every >= 1 - 1e-6 and abs(keep_every - round(keep_every)) <= 1e-6:
        step = tracks.frame_step * round(keep_every)
        on_grid = (tracks.frames - tracks.frames.min()) % step == 0
        return dataclasses.replace(tracks, frames=tracks.frames[on_grid],
                                   pedestrians=tracks.pedestrians[on_grid],
                                   xy=tracks.xy[on_grid] * scale, frame_step=step,
                                   rate_hz=model_hz)
    annotated = (f"{tracks.path}: annotated at {rate:g} Hz (a row every "
                 f"{_frame_ids(tracks.frame_step)} at {fps:g} per second)")
    step_s = 1 / model_hz
    if rate * MAX_INTERPOLATED_STEPS < model_hz * (1 - 1e-6):
        fix = (f"check --fps, or train a model with --step {1 / rate:g}" if own
               else f"a model with --step {1 / rate:g} reads it")
        raise DataError(f"{annotated}, less than 1/{MAX_INTERPOLATED_STEPS:g} of the model's "
                        f"{model_hz:g} Hz: its rows are more than {MAX_INTERPOLATED_STEPS:g} "
                        f"steps of {step_s:g} s apart, too far apart to interpolate; {fix}")
    step_frames = fps * step_s
    if abs(step_frames - round(step_frames)) > 1e-6:
        finer = fractions.Fraction(step_frames).limit_denominator(1000).denominator
        fix = (f"number its frames in finer units (frame ids x{finer}, read with "
               f"--fps {fps * finer:g})" if own else
               f"a model whose step is a whole number of them (a multiple of {1 / fps:g} s) "
               "reads it")
        raise DataError(f"{annotated}, not a multiple of the model's {model_hz:g} Hz, and "
                        f"its {step_s:g} s steps would fall between frame ids "
                        f"({step_frames:.4g} apart); {fix}")
    return interpolate_to_steps(tracks, round(step_frames), scale, model_hz)


def interpolate_to_steps(tracks: Tracks, step: int, scale: float = 1.0,
                         rate_hz: float | None = None) -> Tracks:
    """Each track resampled to the model's steps by linear interpolation (a file whose rate
    is not a multiple of the model's: WILDTRACK's 2 Hz read at 2.5 Hz).

    The steps are the frames `first + k * step` (k = 0, 1, ...; `first` the file's first
    frame, `step` the model's step in frame ids). At a step, a track's position is:
    - its row at that frame, if it has one;
    - else the linear interpolation of its rows just before and just after the step, if those
      are at most 2 steps apart (MAX_INTERPOLATED_STEPS); farther apart (a gap in the file), the
      track is not detected at the steps between (the rule of `Stream.step(..., time=)`);
    - nothing before its first row or after its last: a track is never extrapolated.

    Returns tracks on that grid (frame_step `step`), positions times `scale`.
    """
    order = np.lexsort((tracks.frames, tracks.pedestrians))
    frames, pedestrians, xy = tracks.frames[order], tracks.pedestrians[order], tracks.xy[order]
    first = int(frames.min())
    # A row at a step is kept as it is.
    at_step = (frames - first) % step == 0
    # Each pair of consecutive rows of one track, close enough, gives the steps strictly
    # between them: floor((later - 1 - first) / step) - floor((earlier - first) / step).
    gap = np.diff(frames)
    pairs = np.flatnonzero((pedestrians[1:] == pedestrians[:-1])
                           & (gap <= MAX_INTERPOLATED_STEPS * step))
    earlier, later = frames[pairs], frames[pairs + 1]
    counts = (later - 1 - first) // step - (earlier - first) // step
    pair = np.repeat(np.arange(len(pairs)), counts)
    index = np.arange(len(pair)) - np.repeat(np.cumsum(counts) - counts, counts)
    between = first + ((earlier[pair] - first) // step + 1 + index) * step
    weight = ((between - earlier[pair]) / (later[pair] - earlier[pair]))[:, None]
    start, end = xy[pairs[pair]], xy[pairs[pair] + 1]
    new_frames = np.concatenate([frames[at_step], between])
    new_pedestrians = np.concatenate([pedestrians[at_step], pedestrians[pairs[pair]]])
    new_xy = np.concatenate([xy[at_step], start + weight * (end - start)])
    by_frame = np.lexsort((new_pedestrians, new_frames))
    return dataclasses.replace(tracks, frames=new_frames[by_frame],
                               pedestrians=new_pedestrians[by_frame],
                               xy=new_xy[by_frame] * scale, frame_step=step, rate_hz=rate_hz)


def _frame_ids(count: int) -> str:
    return "frame id" if count == 1 else f"{count} frame ids"


def _frame_grid(frames: np.ndarray, pedestrians: np.ndarray) -> tuple[int, int]:
    """(step, phase) of a file's frame grid: the most common difference between a
    pedestrian's consecutive frames (ETH/UCY 10, LCAS 1, WILDTRACK 5), and the most common
    frame id modulo it. A few rows off that grid do not change it, as a gcd would."""
    order = np.lexsort((frames, pedestrians))
    same = pedestrians[order][1:] == pedestrians[order][:-1]
    steps = np.diff(frames[order])[same]
    steps = steps[steps > 0]
    if not len(steps):                     # nobody seen twice: the gaps between frames
        steps = np.diff(np.unique(frames))
    if not len(steps):
        return 1, 0
    values, counts = np.unique(steps, return_counts=True)
    step = int(values[np.argmax(counts)])
    residues, counts = np.unique(frames % step, return_counts=True)
    return step, int(residues[np.argmax(counts)])
