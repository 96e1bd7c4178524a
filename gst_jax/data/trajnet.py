"""A TrajNet++ file's own scenes, and the window the model reads from each (numpy only).

A TrajNet++ scene row (Kothari et al. 2021) names a primary pedestrian and the frames s to e
of its scene: 21 rows of the file (s, s + d, ..., e; d its frame step), the primary present
at every one. TrajNet++'s evaluator takes the first 9 rows as observed (the current frame
last) and scores the 12 after. The model observes `obs_len` steps and predicts `pred_len`, one
row each: it reads a scene as the window of its last `obs_len` observed rows and its 12
predicted ones, so that its predicted steps are the rows TrajNet++ scores. With the paper's
grid (8 + 12), the scene's first row is the one it does not see:

    row        0   1   2  ...  8 | 9  10  ...  20
    TrajNet++  observed (9)      | predicted (12)
    gst_jax    -   observed (8)  | predicted (12)

A scene's pedestrians are everyone with a row in the window's frames, as in the windows the
split cuts (`gst_jax.data.windows`). TrajNet++'s own neighbours are everyone with a row in the
scene's frames; the truth it scores against is `SceneSet.tracks`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from gst_jax.config import DataConfig, TimeGrid
from gst_jax.data.protocols import split_files, split_frames, why_no_window
from gst_jax.data.readers import Tracks, read_tracks
from gst_jax.data.windows import Window, WindowSet, window_at
from gst_jax.errors import DataError

__all__ = ["OBSERVED_ROWS", "Scene", "SceneSet", "load_scenes", "read_scenes", "trajnet_file"]

# TrajNet++'s observation: the rows of a scene before those it scores (its evaluator's
# obs_length); the model predicts the rest.
OBSERVED_ROWS = 9


@dataclasses.dataclass(frozen=True)
class Scene:
    """One scene row of a TrajNet++ file.

    Attributes:
      scene_id, primary, start, end: its "id", "p", "s" and "e".
      fps, tag: its "fps" and "tag" as the file states them (None where it states none),
        written back unchanged.
      line: its line in the file.
    """

    scene_id: int
    primary: int
    start: int
    end: int
    fps: Any
    tag: Any
    line: int


@dataclasses.dataclass(frozen=True)
class SceneSet:
    """The scenes of one TrajNet++ file that a split holds, in the file's order.

    Attributes:
      path: the file.
      scenes: its scene rows whose frames lie within the split's windows.
      windows: window i is what the model reads of scene i (module docstring): its
        start_frame the scene's row OBSERVED_ROWS - obs_len.
      tracks: the file's tracks in metres, one row a model step: the truth of every scene.
    """

    path: str
    scenes: tuple[Scene, ...]
    windows: WindowSet
    tracks: Tracks

    def __len__(self) -> int:
        return len(self.scenes)

    def frames(self, index: int) -> np.ndarray:
        """(OBSERVED_ROWS + P,) the frames of scene `index`'s rows."""
        scene = self.scenes[index]
        return np.arange(scene.start, scene.end + 1, self.tracks.frame_step)


def read_scenes(path: str | Path) -> tuple[Scene, ...]:
    """The scene rows of a TrajNet++ file, in its order; () for a file without any (or not a
    TrajNet++ file). A scene id given twice, or a field of the wrong type, is refused."""
    path = Path(path)
    if path.suffix != ".ndjson" or not path.is_file():
        return ()
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        return ()                                 # read_tracks names the line and the byte
    scenes: list[Scene] = []
    first_line: dict[int, int] = {}
    for line_number, line in enumerate(text.splitlines(), 1):
        if '"scene"' not in line:
            continue                              # track rows: read_tracks checks them
        try:
            row = json.loads(line).get("scene")
        except (json.JSONDecodeError, AttributeError, RecursionError):
            continue                              # read_tracks names what is wrong with it
        if not isinstance(row, dict):
            continue
        values = {}
        for key in ("id", "p", "s", "e"):
            value = row.get(key)
            if isinstance(value, bool) or not isinstance(value, int):
                raise DataError(f"{path}:{line_number}: scene field {key} must be an integer, "
                                f"got {value!r}")
            values[key] = value
        if values["e"] < values["s"]:
            raise DataError(f"{path}:{line_number}: scene {values['id']} ends (e {values['e']}) "
                            f"before it starts (s {values['s']})")
        if values["id"] in first_line:
            raise DataError(f"{path}:{line_number}: scene {values['id']} again (first at line "
                            f"{first_line[values['id']]}): TrajNet++ pairs scenes by their ids")
        first_line[values["id"]] = line_number
        scenes.append(Scene(values["id"], values["p"], values["s"], values["e"],
                            row.get("fps"), row.get("tag"), line_number))
    return tuple(scenes)


def trajnet_file(config: DataConfig, split: str) -> Path | None:
    """The TrajNet++ file whose scenes `split` of `config` predicts; None where its files are
    not TrajNet++ files with scene rows (their windows are predicted). Several such files are
    refused: TrajNet++ scores one prediction file against one data file."""
    files = split_files(config, split)
    with_scenes = [path for path in files if read_scenes(path)]
    if not with_scenes or len(with_scenes) < len(files):
        return None
    if len(with_scenes) > 1:
        shown = ", ".join(path.name for path in with_scenes[:3])
        more = ", ..." if len(with_scenes) > 3 else ""
        raise DataError(f"{config.scene}: {len(with_scenes)} TrajNet++ files ({shown}{more}): a "
                        "TrajNet++ prediction file answers one of them; give one with --data "
                        "FILE, or --windows for the windows of all of them")
    return with_scenes[0]


def load_scenes(config: DataConfig, split: str, grid: TimeGrid = TimeGrid()
                ) -> SceneSet | None:
    """The TrajNet++ scenes of `split` (those whose frames lie within the split's windows'),
    each with its window on the model's `grid`; None where the data are not one TrajNet++ file
    (`trajnet_file`). A scene the model cannot read row for row is refused in one line."""
    path = trajnet_file(config, split)
    if path is None:
        return None
    if config.scale != 1.0:
        raise DataError(f"{path}: TrajNet++ files are in metres, and its predictions are "
                        "written in metres: --units is for text files")
    covered = [(tracks, first, last) for tracks, first, last in split_frames(config, split, grid)
               if tracks.path == str(path)]
    if not covered:
        raise DataError(f"{path}: the {split} split holds none of its windows: "
                        f"{why_no_window(path, config, split, grid)}")
    tracks, first, last = covered[0]
    _check_rows_are_steps(path, tracks, config, grid)
    if grid.obs_len > OBSERVED_ROWS:
        raise DataError(f"the model observes {grid.obs_len} steps; a TrajNet++ scene holds "
                        f"{OBSERVED_ROWS} observed rows (--windows predicts the split's windows)")
    scenes = tuple(scene for scene in read_scenes(path)
                   if first <= scene.start and scene.end <= last)
    if not scenes:
        raise DataError(f"{path}: none of its scenes lies within the frames of the {split} "
                        f"split's windows ({first}-{last}); --split all predicts every scene")
    windows = tuple(_scene_window(path, scene, tracks, grid) for scene in scenes)
    return SceneSet(str(path), scenes, WindowSet(windows, f"{config.scene}/trajnet/{split}",
                                                 ((str(path), len(windows)),)), tracks)


def rows_grid(config: DataConfig, split: str, grid: TimeGrid = TimeGrid()) -> TimeGrid:
    """The time grid whose steps are the rows of the TrajNet++ file `split` of `config` holds
    scenes of (at its own rate, or --fps), with `grid`'s observed and predicted steps: a
    submission's, which steps once a row (WILDTRACK's 2 Hz: 0.5 s); `grid` where the data are
    not one TrajNet++ file with scenes."""
    path = trajnet_file(config, split)
    if path is None:
        return grid
    rate = _row_rate(read_tracks(path, drop_off_grid=config.drop_off_grid), config, grid)
    return dataclasses.replace(grid, step_s=1 / rate)


def _row_rate(rows: Tracks, config: DataConfig, grid: TimeGrid) -> float:
    """A file's rows per second: --fps frame ids a second, else its stated rate."""
    return (config.fps or (rows.rate_hz or grid.hz) * rows.frame_step) / rows.frame_step


def _check_rows_are_steps(path: Path, tracks: Tracks, config: DataConfig,
                          grid: TimeGrid) -> None:
    """TrajNet++ scores a scene's rows: the model's steps must be the file's rows."""
    rows = read_tracks(path, drop_off_grid=config.drop_off_grid)
    if tracks.frame_step == rows.frame_step and len(tracks.frames) == len(rows.frames):
        return
    rate = _row_rate(rows, config, grid)
    row_fps = rate * rows.frame_step
    raise DataError(
        f"{path}: its rows are {1 / rate:g} s apart ({_frame_ids(rows.frame_step)} at "
        f"{row_fps:g} per second), the model's steps {grid.step_s:g} s: TrajNet++ scores its "
        f"scenes row for row ({OBSERVED_ROWS} observed, {grid.pred_len} predicted), so the "
        f"model must step once a row: a model with --step {1 / rate:g}, or --data {path} "
        f"--fps {grid.hz * rows.frame_step:g} to read its rows as {grid.step_s:g} s apart "
        "(as TrajNet++'s own baselines do, whatever a file's rate); or --windows")


def _scene_window(path: Path, scene: Scene, tracks: Tracks, grid: TimeGrid) -> Window:
    """What the model reads of `scene`: its last obs_len observed rows and the predicted."""
    step, rows = tracks.frame_step, OBSERVED_ROWS + grid.pred_len
    where = f"{path}:{scene.line}: scene {scene.scene_id}"
    if scene.end - scene.start != (rows - 1) * step:
        raise DataError(f"{where} spans frames {scene.start}-{scene.end}, "
                        f"{(scene.end - scene.start) / step + 1:g} rows of "
                        f"{_frame_ids(step)}; "
                        f"a TrajNet++ scene holds {OBSERVED_ROWS} observed rows and the "
                        f"model's {grid.pred_len} predicted ({rows})")
    frames = scene.start + step * np.arange(rows)
    present = np.isin(frames, tracks.frames[tracks.pedestrians == scene.primary])
    if not present.all():
        raise DataError(f"{where}: its primary pedestrian {scene.primary} has no row at frame "
                        f"{int(frames[np.argmin(present)])}; a TrajNet++ scene holds its "
                        f"primary at every row ({scene.start}-{scene.end})")
    start = int(frames[OBSERVED_ROWS - grid.obs_len])
    window = window_at(tracks, start, grid.seq_len, grid.obs_len)
    assert window is not None, "the primary is detected at every step"
    return window


def _frame_ids(count: int) -> str:
    return "1 frame id" if count == 1 else f"{count} frame ids"
