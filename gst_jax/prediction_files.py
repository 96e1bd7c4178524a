"""Predictions as files, in the TrajNet++ ndjson format, and back.

One scene row per window of the split (its index, first and last frame), the observed tracks,
then K sampled futures of every predicted pedestrian, one row per step and sample:

    {"scene": {"id": 3, "p": 17, "s": 120, "e": 310, "fps": 2.5, "tag": 0}}
    {"track": {"f": 120, "p": 17, "x": 4.12, "y": 7.9}}
    {"track": {"f": 200, "p": 17, "x": 5.3, "y": 8.1, "prediction_number": 0, "scene_id": 3}}

Frames are the data's own frame ids, coordinates metres in the data's own frame (the windows'
origins added back), written at full precision, so that a file scores exactly as the
predictions it was written from. TrajNet++ names the scene's primary pedestrian "p"; every
pedestrian is predicted here, and "p" is the first of them.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple

import numpy as np

from gst_jax import data
from gst_jax.config import TimeGrid
from gst_jax.data import SceneBatch
from gst_jax.errors import DataError


class PredictedBatch(NamedTuple):
    """K sampled futures of a batch of windows (`data.evaluation_batches`).

    batch: the windows with their future, padded to N; positions: (K, B, P, N, 2), NaN where
    nobody was predicted, None where a baseline alone is scored; predicted_mask: (B, N) the
    pedestrians predicted.
    """

    batch: SceneBatch
    positions: np.ndarray | None
    predicted_mask: np.ndarray


def write_predictions(path: Path, window_set: data.WindowSet,
                      predicted: Iterable[PredictedBatch], grid: TimeGrid) -> int:
    """Write every window's observations and sampled futures on the model's time `grid`;
    returns the rows written.

    The file appears only when complete (written beside it, then renamed).
    """
    rows, partial = 0, partial_path(path)
    try:
        with open(partial, "w") as out:
            for batch, positions, predicted_mask in predicted:
                assert positions is not None, "a baseline's batch has no predictions to write"
                for b, index in enumerate(np.asarray(batch.window_index)):
                    if not batch.scene_mask[b]:
                        continue
                    window = window_set[int(index)]
                    lines = _window_rows(int(index), window, positions[:, b],
                                         predicted_mask[b], grid)
                    out.write("".join(line + "\n" for line in lines))
                    rows += len(lines)
    except BaseException:             # a full disk, Ctrl-C, SIGTERM: no half file is left
        partial.unlink(missing_ok=True)
        raise
    os.replace(partial, path)
    return rows


def partial_path(path: Path) -> Path:
    """Where `write_predictions` writes before the file is complete."""
    return path.with_name(f"{path.name}.partial")


def check_output(path: Path, inputs: Iterable[Path]) -> None:
    """Refuse, before anything is computed, an output that would destroy something: one that
    exists and is not a regular file (a folder, a device, a FIFO), or that is one of the
    `inputs` (the data being predicted); and one whose folder does not exist."""
    if path.exists() or path.is_symlink():
        if not path.is_file():
            raise DataError(f"{path} exists and is not a regular file: --out names the "
                            "prediction file to write")
        for data_file in inputs:
            if data_file.exists() and os.path.samefile(path, data_file):
                raise DataError(f"{path} is the data being predicted: --out must name another "
                                "file")
    if not path.parent.is_dir():
        raise DataError(f"{path.parent}: no such folder for --out")


def _window_rows(index: int, window: data.Window, futures: np.ndarray, predicted: np.ndarray,
                 grid: TimeGrid) -> list[str]:
    """futures (K, P, N, 2) relative to the window's origin; predicted (N,)."""
    obs_len = grid.obs_len
    ids = [int(p) for p in window.pedestrian_ids]
    slots = [n for n in range(len(ids)) if predicted[n] > 0]
    first, last = window.frame_range
    lines = [json.dumps({"scene": {"id": index, "p": ids[slots[0]] if slots else ids[0],
                                   "s": first, "e": last, "fps": grid.hz, "tag": 0}})]
    for t, n in zip(*np.nonzero(window.position_mask[:obs_len])):
        x, y = window.positions[t, n] + window.origin
        lines.append(json.dumps({"track": {"f": _frame(window, t), "p": ids[n],
                                           "x": float(x), "y": float(y)}}))
    for k in range(futures.shape[0]):
        for n in slots:
            for t in range(futures.shape[1]):
                x, y = futures[k, t, n] + window.origin
                lines.append(json.dumps({"track": {
                    "f": _frame(window, obs_len + t), "p": ids[n], "x": float(x),
                    "y": float(y), "prediction_number": k, "scene_id": index}}))
    return lines


def _frame(window: data.Window, step: int) -> int:
    return int(window.start_frame + step * window.frame_step)


def read_predictions(path: Path, window_set: data.WindowSet, obs_len: int
                     ) -> Iterator[PredictedBatch]:
    """The predictions of a TrajNet++ file for the windows of `window_set`, in the batches of
    `data.evaluation_batches`. Every fully detected pedestrian (those scored) must have all K
    samples at every future step; a `DataError` names the file, line and what was wrong."""
    samples = _read_samples(Path(path), window_set)
    num_samples = 1 + max((k for (_, _, _, k) in samples), default=-1)
    if num_samples == 0:
        raise DataError(f"{path}: no predicted track (rows with a prediction_number)")
    for batch in data.evaluation_batches(window_set):
        scene_count, steps, slots = batch.positions.shape[:3]
        pred_len = steps - obs_len
        positions = np.full((num_samples, scene_count, pred_len, slots, 2), np.nan, np.float32)
        scored = batch.fully_detected_mask * batch.scene_mask[:, None]
        for b, index in enumerate(np.asarray(batch.window_index)):
            if not batch.scene_mask[b]:
                continue
            window = window_set[int(index)]
            for n, pedestrian in enumerate(window.pedestrian_ids):
                for k in range(num_samples):
                    for t in range(pred_len):
                        frame = _frame(window, obs_len + t)
                        xy = samples.get((int(index), int(pedestrian), frame, k))
                        if xy is not None:
                            positions[k, b, t, n] = np.asarray(xy) - window.origin
        predicted_mask = np.all(np.isfinite(positions), axis=(0, 2, 4)).astype(np.float32)
        missing = np.argwhere((scored > 0) & (predicted_mask == 0))
        if len(missing):
            b, n = missing[0]
            window = window_set[int(batch.window_index[b])]
            raise DataError(f"{path}: pedestrian {int(window.pedestrian_ids[n])} of scene "
                            f"{int(batch.window_index[b])} is scored (fully detected) but lacks "
                            f"some of its {num_samples} x {pred_len} predicted positions")
        yield PredictedBatch(batch, positions, predicted_mask)


def _read_samples(path: Path, window_set: data.WindowSet
                  ) -> dict[tuple[int, int, int, int], tuple[float, float]]:
    """(scene, pedestrian, frame, sample) -> (x, y) of every predicted row; checks each row."""
    samples = {}
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except UnicodeDecodeError as error:
        raise DataError(f"{path}: not UTF-8 text ({error.reason} at byte {error.start})") from None
    for line_number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        where = f"{path}:{line_number}"
        try:
            row = json.loads(line)
        except json.JSONDecodeError as error:
            raise DataError(f"{where}: not JSON ({error.msg})") from None
        row = row if isinstance(row, dict) else {}
        if isinstance(row.get("scene"), dict):
            _check_scene(where, row["scene"], window_set)
            continue
        track = row.get("track")
        if not isinstance(track, dict):
            raise DataError(f"{where}: expected a scene or a track row")
        if "prediction_number" not in track:
            continue                            # an observation: the truth comes from the data
        f, p, k, scene = (_integer(where, track, name)
                          for name in ("f", "p", "prediction_number", "scene_id"))
        if not 0 <= scene < len(window_set):
            raise DataError(f"{where}: scene_id {scene} is not a window of the data "
                            f"({len(window_set)} windows)")
        if k < 0:
            raise DataError(f"{where}: prediction_number {k} is negative")
        samples[scene, p, f, k] = (_number(where, track, "x"), _number(where, track, "y"))
    return samples


def _check_scene(where: str, scene, window_set: data.WindowSet) -> None:
    """A scene row must describe the window of the same index: same first and last frame."""
    index, first, last = (_integer(where, scene, name) for name in ("id", "s", "e"))
    if not 0 <= index < len(window_set):
        raise DataError(f"{where}: scene {index} is not a window of the data "
                        f"({len(window_set)} windows)")
    if window_set[index].frame_range != (first, last):
        expected = window_set[index].frame_range
        raise DataError(f"{where}: scene {index} covers frames {first}-{last}, but window "
                        f"{index} of the data covers {expected[0]}-{expected[1]}: were the "
                        "predictions made for this data and split?")


def _integer(where: str, fields: dict, name: str) -> int:
    value = fields.get(name)
    if isinstance(value, bool) or not isinstance(value, int):
        raise DataError(f"{where}: {name} must be an integer, got {value!r}")
    return value


def _number(where: str, fields: dict, name: str) -> float:
    value = fields.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise DataError(f"{where}: {name} must be a finite number, got {value!r}")
    return float(value)
