"""Scene windows of partially detected pedestrians (docs/MODEL.md 1), numpy only."""

from __future__ import annotations

import dataclasses
from typing import Iterable, Sequence

import numpy as np

from gst_jax.data.batch import fully_detected, node_mask_from_positions, predicted
from gst_jax.data.readers import Tracks


@dataclasses.dataclass(frozen=True)
class Window:
    """One scene window: T steps of the N_w pedestrians seen in it.

    Its pedestrians come in three groups, each in id order: first the `num_predicted` the
    model predicts (valid at the last observed step, docs/MODEL.md 2.3), then those valid at
    some earlier observed step only, then those seen only after the observation, which the
    model never sees. So the prediction steps compute on the first slots only, and training
    leaves the last group out (`gst_jax.data.pack_step`).

    Attributes:
      positions: (T, N_w, 2) float32 metres relative to `origin`, zero where the pedestrian
        was not detected.
      position_mask: (T, N_w) float32, 1 where the position exists.
      pedestrian_ids: (N_w,) int64, in the order above.
      source: the file the window was cut from.
      start_frame: frame id of step 0; step t is frame start_frame + t * frame_step.
      frame_step: frame-id difference of one step.
      obs_len: observed steps (the first obs_len of the T).
      origin: (2,) float64 metres subtracted from the file's coordinates before the float32
        cast: the nearest whole kilometre of the window's mean position, so that positions
        of UTM-like data (near 1e6-1e9 m) keep their millimetres; 0 for local coordinates.
    """

    positions: np.ndarray
    position_mask: np.ndarray
    pedestrian_ids: np.ndarray
    source: str
    start_frame: int
    frame_step: int
    obs_len: int
    origin: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(2))

    @property
    def num_pedestrians(self) -> int:
        return self.position_mask.shape[1]

    @property
    def frame_range(self) -> tuple[int, int]:
        """(first, last) frame id covered by the window's time grid."""
        last = self.start_frame + (self.position_mask.shape[0] - 1) * self.frame_step
        return self.start_frame, last

    @property
    def num_observed(self) -> int:
        """Pedestrians valid at some observed step (the first slots)."""
        return int(np.sum(_groups(self.position_mask, self.obs_len) <= OBSERVED))

    @property
    def num_predicted(self) -> int:
        """Pedestrians the model predicts: valid at the last observed step (the first slots)."""
        return int(np.sum(_groups(self.position_mask, self.obs_len) == PREDICTED))

    def fully_detected(self) -> np.ndarray:
        """(N_w,) bool: detected at every step (docs/MODEL.md 1.8)."""
        return fully_detected(node_mask_from_positions(self.position_mask)) > 0


@dataclasses.dataclass(frozen=True)
class WindowSet:
    """The windows of one split of one dataset, in a fixed order.

    files: (file, windows it gave this split) for every file read, also those that gave none
    (shorter than a window, or without a fully detected pedestrian in any).
    """

    windows: tuple[Window, ...]
    name: str = ""
    files: tuple[tuple[str, int], ...] = ()

    def __len__(self) -> int:
        return len(self.windows)

    def __getitem__(self, index: int) -> Window:
        return self.windows[index]

    def subset(self, indices: Iterable[int]) -> "WindowSet":
        return WindowSet(tuple(self.windows[i] for i in indices), self.name, self.files)

    def files_without_windows(self) -> list[str]:
        return [path for path, count in self.files if count == 0]

    def stats(self) -> dict[str, int]:
        """Counts in the schema of tests/fixtures/reference_windows.json."""
        sizes = [w.num_pedestrians for w in self.windows]
        return {"windows": len(self.windows), "pedestrian_slots": int(sum(sizes)),
                "max_pedestrians": int(max(sizes, default=0)),
                "fully_detected": int(sum(w.fully_detected().sum() for w in self.windows))}


def cut_windows(tracks: Tracks, seq_len: int, obs_len: int) -> list[Window | None]:
    """Every window start of a file, as the release enumerates them (obs_len of the seq_len
    steps observed).

    Start index i runs over range(num_windows + 1) with num_windows = len(frames) - seq_len + 1
    (the release's off-by-one; the last start has too few frames and is never kept). Entry i
    is None when no pedestrian of window i is fully detected (such windows are dropped).
    """
    frames = np.unique(tracks.frames)
    num_windows = len(frames) - seq_len + 1
    frame_index = np.searchsorted(frames, tracks.frames)
    windows: list[Window | None] = []
    for start in range(max(num_windows + 1, 0)):
        rows = (frame_index >= start) & (frame_index < start + seq_len)
        windows.append(_window_from_rows(tracks, rows, int(frames[start]) if start < len(frames)
                                         else 0, seq_len, obs_len))
    return windows


def window_at(tracks: Tracks, start_frame: int, seq_len: int, obs_len: int) -> Window | None:
    """The window of `seq_len` steps from `start_frame` (a frame of the tracks' grid), as
    `cut_windows` cuts them; None when nobody in it is fully detected."""
    last = start_frame + (seq_len - 1) * tracks.frame_step
    rows = (tracks.frames >= start_frame) & (tracks.frames <= last)
    return _window_from_rows(tracks, rows, start_frame, seq_len, obs_len)


def _window_from_rows(tracks: Tracks, rows: np.ndarray, start_frame: int,
                      seq_len: int, obs_len: int) -> Window | None:
    if not rows.any():
        return None
    pedestrian_ids, slot = np.unique(tracks.pedestrians[rows], return_inverse=True)
    offset = tracks.frames[rows] - start_frame
    step = offset // tracks.frame_step
    on_grid = (offset % tracks.frame_step == 0) & (step < seq_len)
    xy = tracks.xy[rows][on_grid]
    origin = np.round(xy.mean(axis=0), -3) if len(xy) else np.zeros(2)
    positions = np.zeros((seq_len, len(pedestrian_ids), 2), np.float32)
    position_mask = np.zeros((seq_len, len(pedestrian_ids)), np.float32)
    positions[step[on_grid], slot[on_grid]] = xy - origin
    position_mask[step[on_grid], slot[on_grid]] = 1.0
    if not fully_detected(node_mask_from_positions(position_mask)).any():
        return None
    order = np.argsort(_groups(position_mask, obs_len), kind="stable")     # then id order
    return Window(positions[:, order], position_mask[:, order], pedestrian_ids[order],
                  tracks.path, start_frame, tracks.frame_step, obs_len, origin)


# A window's pedestrian groups, in the order its slots list them (see Window).
PREDICTED, OBSERVED, UNOBSERVED = 0, 1, 2


def _groups(position_mask: np.ndarray, obs_len: int) -> np.ndarray:
    """(T, N) position mask -> (N,) group of each pedestrian: PREDICTED (valid at the last
    observed step), OBSERVED (valid at an earlier observed step only) or UNOBSERVED."""
    node_mask = node_mask_from_positions(position_mask)
    return np.where(predicted(node_mask, obs_len) > 0, PREDICTED,
                    np.where(node_mask[:obs_len].any(axis=0), OBSERVED, UNOBSERVED))


def kept(windows: Sequence[Window | None]) -> list[Window]:
    return [w for w in windows if w is not None]
