"""Predictions as files, in the TrajNet++ ndjson format, and back.

Two kinds of file. For a TrajNet++ file's own scenes (`gst_jax.data.trajnet`), a submission
as TrajNet++'s evaluator reads it: each scene row of the data in its order (its id, primary,
frames, fps and tag), then K sampled futures of its primary and of every neighbour the model
predicts, the primary first, one row per predicted row of the scene and sample:

    {"scene": {"id": 253, "p": 725, "s": 799, "e": 819, "fps": 2.5, "tag": [1, []]}}
    {"track": {"f": 808, "p": 725, "x": 4.12, "y": 7.9, "prediction_number": 0, "scene_id": 253}}

For the windows of a split (`write_predictions`, any data), one scene row per window (its
index, first and last frame), the observed tracks, then K sampled futures of every predicted
pedestrian; "p" is the first of them, not a TrajNet++ primary:

    {"scene": {"id": 3, "p": 17, "s": 120, "e": 310, "fps": 2.5, "tag": 0}}
    {"track": {"f": 120, "p": 17, "x": 4.12, "y": 7.9}}
    {"track": {"f": 200, "p": 17, "x": 5.3, "y": 8.1, "prediction_number": 0, "scene_id": 3}}

Frames are the data's own frame ids, coordinates metres in the data's own frame (the windows'
origins added back), written at full precision, so that a file scores exactly as the
predictions it was written from.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable, Iterator, NamedTuple, Sequence

import numpy as np

from gst_jax import data
from gst_jax.config import TimeGrid
from gst_jax.data import SceneBatch
from gst_jax.data.trajnet import Scene, SceneSet
from gst_jax.errors import DataError

# A predicted position's key: (scene id, pedestrian, frame, sample).
_SampleKey = tuple[int, int, int, int]


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
    def lines() -> Iterator[list[str]]:
        for batch, positions, predicted_mask in predicted:
            assert positions is not None, "a baseline's batch has no predictions to write"
            for b, index in enumerate(np.asarray(batch.window_index)):
                if batch.scene_mask[b]:
                    yield _window_rows(int(index), window_set[int(index)], positions[:, b],
                                       predicted_mask[b], grid)
    return _write_complete(path, lines())


def write_scene_predictions(path: Path, scene_set: SceneSet,
                            predicted: Iterable[PredictedBatch], grid: TimeGrid) -> int:
    """Write a TrajNet++ submission: each scene of `scene_set` in its file's order, with the
    sampled futures of its primary and of the neighbours predicted with it (`predicted`: the
    batches of `scene_set.windows`, in any order); returns the rows written.

    The file appears only when complete (written beside it, then renamed).
    """
    def lines() -> Iterator[list[str]]:
        futures: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for batch, positions, predicted_mask in predicted:
            assert positions is not None, "a baseline's batch has no predictions to write"
            for b, index in enumerate(np.asarray(batch.window_index)):
                if batch.scene_mask[b]:
                    futures[int(index)] = positions[:, b], predicted_mask[b]
        for index, scene in enumerate(scene_set.scenes):
            yield _scene_rows(scene, scene_set.windows[index], *futures[index], grid)
    return _write_complete(path, lines())


def _write_complete(path: Path, chunks: Iterable[list[str]]) -> int:
    """Write the lines of every chunk beside `path`, then rename: no half file is left."""
    rows, partial = 0, partial_path(path)
    try:
        with open(partial, "w") as out:
            for lines in chunks:
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


def _scene_rows(scene: Scene, window: data.Window, futures: np.ndarray, predicted: np.ndarray,
                grid: TimeGrid) -> list[str]:
    """A TrajNet++ scene's row and its predicted rows, sample by sample, the primary first.
    futures (K, P, N, 2) relative to the window's origin; predicted (N,)."""
    ids = [int(p) for p in window.pedestrian_ids]
    primary = ids.index(scene.primary)
    assert predicted[primary] > 0, "a scene's primary is detected at its current frame"
    slots = [primary] + [n for n in range(len(ids)) if predicted[n] > 0 and n != primary]
    fields = {"id": scene.scene_id, "p": scene.primary, "s": scene.start, "e": scene.end}
    fields.update({key: value for key, value in (("fps", scene.fps), ("tag", scene.tag))
                   if value is not None})
    lines = [json.dumps({"scene": fields})]
    for k in range(futures.shape[0]):
        for n in slots:
            for t in range(futures.shape[1]):
                x, y = futures[k, t, n] + window.origin
                lines.append(json.dumps({"track": {
                    "f": _frame(window, grid.obs_len + t), "p": ids[n], "x": float(x),
                    "y": float(y), "prediction_number": k, "scene_id": scene.scene_id}}))
    return lines


def _frame(window: data.Window, step: int) -> int:
    return int(window.start_frame + step * window.frame_step)


class PredictionFile(NamedTuple):
    """A prediction file read and checked against the scenes of the data it answers.

    path: the file; scene_rows: its scene rows in order, (line, id, p, s, e) each; samples:
    every predicted position (x, y) by (scene id, pedestrian, frame, sample); num_samples: K,
    one more than the largest prediction_number.
    """

    path: Path
    scene_rows: list[tuple[int, int, int, int, int]]
    samples: dict[_SampleKey, tuple[float, float]]
    num_samples: int


class _Expected(NamedTuple):
    """The scenes a file may name: their id -> (first, last frame); what they are, to say so."""

    frames: dict[int, tuple[int, int]]
    kind: str                   # "window": the split's windows; "scene": TrajNet++'s scenes


def read_predictions(path: Path, window_set: data.WindowSet, obs_len: int,
                     scenes: Sequence[Scene] | None = None) -> Iterator[PredictedBatch]:
    """The predictions of a TrajNet++ file for the windows of `window_set`, in the batches of
    `data.evaluation_batches`. Every fully detected pedestrian (those scored) must have all K
    samples at every future step; a `DataError` names the file, line and what was wrong.
    scenes: the TrajNet++ scenes the windows were read from (`SceneSet.scenes`): the file's
    scene ids and frames are theirs; None: the windows' own indices and frame ranges."""
    file = read_prediction_file(path, window_set, scenes)
    return predicted_batches(file, window_set, obs_len, scenes)


def read_prediction_file(path: Path, window_set: data.WindowSet,
                         scenes: Sequence[Scene] | None = None) -> PredictionFile:
    """Read a prediction file, every row checked: its scene rows against the windows of
    `window_set` (or the TrajNet++ `scenes` they were read from), its predicted rows' scene
    ids among them."""
    if scenes is None:
        expected = _Expected({i: window.frame_range
                              for i, window in enumerate(window_set.windows)}, "window")
    else:
        expected = _Expected({scene.scene_id: (scene.start, scene.end) for scene in scenes},
                             "scene")
    scene_rows, samples = _read_samples(Path(path), expected)
    num_samples = 1 + max((k for (_, _, _, k) in samples), default=-1)
    if num_samples == 0:
        raise DataError(f"{path}: no predicted track (rows with a prediction_number)")
    return PredictionFile(Path(path), scene_rows, samples, num_samples)


def predicted_batches(file: PredictionFile, window_set: data.WindowSet, obs_len: int,
                      scenes: Sequence[Scene] | None = None) -> Iterator[PredictedBatch]:
    """`read_predictions` of a file already read."""
    path, samples, num_samples = file.path, file.samples, file.num_samples
    for batch in data.evaluation_batches(window_set):
        scene_count, steps, slots = batch.positions.shape[:3]
        pred_len = steps - obs_len
        positions = np.full((num_samples, scene_count, pred_len, slots, 2), np.nan, np.float32)
        scored = batch.fully_detected_mask * batch.scene_mask[:, None]
        for b, index in enumerate(np.asarray(batch.window_index)):
            if not batch.scene_mask[b]:
                continue
            window = window_set[int(index)]
            scene_id = int(index) if scenes is None else scenes[int(index)].scene_id
            for n, pedestrian in enumerate(window.pedestrian_ids):
                for k in range(num_samples):
                    for t in range(pred_len):
                        frame = _frame(window, obs_len + t)
                        xy = samples.get((scene_id, int(pedestrian), frame, k))
                        if xy is not None:
                            positions[k, b, t, n] = np.asarray(xy) - window.origin
        predicted_mask = np.all(np.isfinite(positions), axis=(0, 2, 4)).astype(np.float32)
        missing = np.argwhere((scored > 0) & (predicted_mask == 0))
        if len(missing):
            b, n = missing[0]
            index = int(batch.window_index[b])
            scene_id = index if scenes is None else scenes[index].scene_id
            raise DataError(f"{path}: pedestrian {int(window_set[index].pedestrian_ids[n])} "
                            f"of scene {scene_id} is scored (fully detected) but lacks "
                            f"some of its {num_samples} x {pred_len} predicted positions")
        yield PredictedBatch(batch, positions, predicted_mask)


def _read_samples(path: Path, expected: _Expected
                  ) -> tuple[list[tuple[int, int, int, int, int]],
                             dict[_SampleKey, tuple[float, float]]]:
    """The scene rows (line, id, p, s, e) and (scene, pedestrian, frame, sample) -> (x, y) of
    every predicted row; checks each row."""
    scene_rows, samples = [], {}
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
            scene_rows.append((line_number, *_check_scene(where, row["scene"], expected)))
            continue
        track = row.get("track")
        if not isinstance(track, dict):
            raise DataError(f"{where}: expected a scene or a track row")
        if "prediction_number" not in track:
            continue                            # an observation: the truth comes from the data
        f, p, k, scene = (_integer(where, track, name)
                          for name in ("f", "p", "prediction_number", "scene_id"))
        if scene not in expected.frames:
            raise DataError(f"{where}: scene_id {scene} is not {_among(expected)}")
        if k < 0:
            raise DataError(f"{where}: prediction_number {k} is negative")
        samples[scene, p, f, k] = (_number(where, track, "x"), _number(where, track, "y"))
    return scene_rows, samples


def _among(expected: _Expected) -> str:
    count = len(expected.frames)
    if expected.kind == "window":
        return f"a window of the data ({count} windows)"
    return f"a TrajNet++ scene of the data's split ({count} scenes)"


def _check_scene(where: str, scene, expected: _Expected) -> tuple[int, int, int, int]:
    """A scene row must describe the window (or TrajNet++ scene) of the same id: same first
    and last frame. Returns its id, p, s, e."""
    index, first, last = (_integer(where, scene, name) for name in ("id", "s", "e"))
    if index not in expected.frames:
        raise DataError(f"{where}: scene {index} is not {_among(expected)}")
    if expected.frames[index] != (first, last):
        shown = expected.frames[index]
        hint = ("" if expected.kind == "window" else "; a file of the split's windows "
                "(`predict --windows`) is scored with --windows")
        raise DataError(f"{where}: scene {index} covers frames {first}-{last}, but "
                        f"{expected.kind} {index} of the data covers {shown[0]}-{shown[1]}: "
                        f"were the predictions made for this data and split?{hint}")
    return index, _integer(where, scene, "p"), first, last


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
