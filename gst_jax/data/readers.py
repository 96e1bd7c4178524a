"""Readers of raw trajectory files into validated `Tracks` (numpy only).

Every problem with an input file is reported as a `DataError` naming the file, the line and
what is wrong, before any array is built: a bad file never turns into a silently wrong window.
"""

from __future__ import annotations

import dataclasses
import json
import math
from functools import reduce
from pathlib import Path

import numpy as np


class DataError(ValueError):
    """A data file or request that cannot be used; the message says where and why."""


@dataclasses.dataclass(frozen=True)
class Tracks:
    """All annotated rows of one file, sorted by (frame, pedestrian).

    Attributes:
      path: the file the rows came from.
      frames: (R,) int64 frame ids.
      pedestrians: (R,) int64 pedestrian ids.
      xy: (R, 2) float64 positions in metres.
      frame_step: frame-id difference between consecutive annotation steps (0.4 s).
    """

    path: str
    frames: np.ndarray
    pedestrians: np.ndarray
    xy: np.ndarray
    frame_step: int


def read_tracks(path: str | Path) -> Tracks:
    """Read a raw ETH/UCY text file (`.txt`) or a TrajNet++ file (`.ndjson`)."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file")
    if path.suffix == ".ndjson":
        return read_trajnet_ndjson(path)
    return read_text_tracks(path)


def read_text_tracks(path: str | Path) -> Tracks:
    """`frame ped x y` rows, tab- or space-separated, as in the ETH/UCY raw files."""
    path = Path(path)
    rows = []
    for line_number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        fields = line.split()
        if len(fields) != 4:
            raise DataError(f"{path}:{line_number}: expected 4 columns (frame ped x y), "
                            f"found {len(fields)}: {line.strip()!r}")
        rows.append(_parse_row(path, line_number, fields))
    return _build_tracks(path, rows)


def read_trajnet_ndjson(path: str | Path) -> Tracks:
    """TrajNet++ ndjson: `{"track": {"f", "p", "x", "y"}}` rows; `{"scene": ...}` rows skipped."""
    path = Path(path)
    rows = []
    for line_number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            raise DataError(f"{path}:{line_number}: not valid JSON ({error.msg})") from None
        if not isinstance(record, dict) or not ({"scene", "track"} & record.keys()):
            raise DataError(f"{path}:{line_number}: expected a 'scene' or 'track' record")
        if "scene" in record:
            continue
        track = record["track"]
        missing = [k for k in ("f", "p", "x", "y") if k not in track]
        if missing:
            raise DataError(f"{path}:{line_number}: track record lacks {', '.join(missing)}")
        rows.append(_parse_row(path, line_number, [track[k] for k in ("f", "p", "x", "y")]))
    return _build_tracks(path, rows)


def _parse_row(path: Path, line_number: int, fields: list) -> tuple[int, int, float, float, int]:
    names = ("frame", "pedestrian id", "x", "y")
    values = []
    for name, field in zip(names, fields):
        try:
            value = float(field)
        except (TypeError, ValueError):
            raise DataError(f"{path}:{line_number}: {name} is not a number: {field!r}") from None
        if not math.isfinite(value):
            raise DataError(f"{path}:{line_number}: {name} is not finite: {field!r}")
        values.append(value)
    frame, pedestrian, x, y = values
    for name, value in (("frame", frame), ("pedestrian id", pedestrian)):
        if value != int(value):
            raise DataError(f"{path}:{line_number}: {name} is not an integer: {value!r}")
    return int(frame), int(pedestrian), x, y, line_number


def _build_tracks(path: Path, rows: list) -> Tracks:
    if not rows:
        raise DataError(f"{path}: empty file (no trajectory rows)")
    seen: dict[tuple[int, int], int] = {}
    for frame, pedestrian, _, _, line_number in rows:
        first = seen.setdefault((frame, pedestrian), line_number)
        if first != line_number:
            raise DataError(f"{path}:{line_number}: duplicate row for frame {frame}, pedestrian "
                            f"{pedestrian} (first at line {first})")
    table = np.array([row[:4] for row in rows], dtype=np.float64)
    order = np.lexsort((table[:, 1], table[:, 0]))
    table = table[order]
    frames = table[:, 0].astype(np.int64)
    unique_frames = np.unique(frames)
    # The annotation step is read from the data (ETH/UCY 10, LCAS 1, WILDTRACK 5).
    steps = np.diff(unique_frames)
    frame_step = int(reduce(math.gcd, steps.tolist(), 0)) if len(steps) else 1
    return Tracks(path=str(path), frames=frames, pedestrians=table[:, 1].astype(np.int64),
                  xy=table[:, 2:4].copy(), frame_step=max(frame_step, 1))
