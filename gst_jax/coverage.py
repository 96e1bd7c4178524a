"""Coverage of conformal regions over a recorded scene played as a stream (what
`python -m gst_jax.conformal` reports).

A file's frames are fed to a `gst_jax.stream.Stream` one model step at a time, from the first
frame of the split's first window to its end; every prediction is scored at horizon k when
the position k steps later is observed. The first `calibration` fraction of the frames
calibrates split conformal (the ceil((n+1)(1-alpha))-th smallest of their scores, per
horizon step); every method's coverage and mean radius are then measured on the frames
after it, the same predictions for all: long-run coverage = the fraction of scored
predictions whose observed position fell within the radius issued with them.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Iterator

import jax.numpy as jnp
import numpy as np

from gst_jax import conformal, data
from gst_jax.config import DataConfig
from gst_jax.data.readers import Tracks
from gst_jax.progress import Progress
from gst_jax.stream import Regions, Stream

METHODS = ("split", "aci", "dtaci")

FrameRows = tuple[int, np.ndarray, np.ndarray]     # frame id, track ids (M,), positions (M, 2)


def frames(tracks: Tracks, first: int, last: int) -> Iterator[FrameRows]:
    """(frame id, track ids (M,), positions (M, 2)) of every step of the file's grid from
    frame `first` to `last`, steps without detections included."""
    for frame in range(first, last + 1, tracks.frame_step):
        rows = tracks.frames == frame
        yield frame, tracks.pedestrians[rows], tracks.xy[rows]


def live_tracks(frames_of_file: list[FrameRows], obs_len: int) -> int:
    """The most tracks a stream holds at once over these frames: the ids seen within any
    `obs_len` consecutive frames (a stream sized so never grows, never recompiles)."""
    seen = [set(ids.tolist()) for _, ids, _ in frames_of_file]
    return max([len(set().union(*seen[max(0, t - obs_len + 1):t + 1]))
                for t in range(len(seen))], default=1)


@dataclasses.dataclass
class Snapshot:
    """One frame's regions, for a figure: the frame after calibration predicting the most
    tracks. history (L, T, 2) NaN where not detected; futures (L, P, 2); radii (L, P);
    truth (L, P, 2) the positions observed later, NaN where not."""

    frame: int
    history: np.ndarray
    futures: np.ndarray
    radii: np.ndarray
    truth: np.ndarray


def play(run, streams: list[Iterator[FrameRows]], *, method: str, alpha: float = 0.1,
         pooled: bool = True, calibration: float = 0.3, convention: str = "gst",
         seed: int = 0, progress: Progress | None = None) -> tuple[dict, Snapshot | None]:
    """Coverage and mean radius per horizon step of `method` over the streams (iterators of
    frames, played one after another, each with a fresh stream and regions), and the
    snapshot of one frame (None if no frame after calibration predicts anyone)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not 0 < alpha < 1 or not 0 <= calibration < 1:
        raise ValueError(f"alpha must lie in (0, 1) and calibration in [0, 1), got {alpha} and "
                         f"{calibration}")
    streams = [list(s) for s in streams]
    total = sum(len(s) for s in streams)
    calibrating = round(calibration * total)
    horizon = run.model_config.pred_len
    regions = Regions(None if method == "split" else method, alpha, pooled)
    scored = []                                  # (scores, mask, issued) (C, P) per frame
    best = None                                  # (tracks, frame index, file, output, history)
    started = time.perf_counter()
    for frames_of_file in streams:
        player = Stream(run, regions=regions, convention=convention, seed=seed,
                        capacity=live_tracks(frames_of_file, run.model_config.obs_len))
        for index, (frame, ids, xy) in enumerate(frames_of_file):
            out = player.step(ids, xy)
            scored.append((out.delayed.scores, out.delayed.mask, out.delayed.issued))
            if len(scored) > calibrating and (best is None or len(out.ids) > best[0]):
                best = (len(out.ids), index, frames_of_file, out, _histories(player, out.ids))
            if progress:
                progress.count("frames", len(scored), total, started)
    calibration_scores = np.concatenate(                        # (P, n), NaN where none
        [np.where(m, s, np.nan).T for s, m, _ in scored[:calibrating]] or
        [np.zeros((horizon, 0))], axis=1)
    result = {"method": method, "alpha": alpha, "pooled": pooled, "frames": total,
              "calibration_frames": calibrating, "step_s": run.model_config.step_s}
    split_radii = None
    if method == "split":
        valid = np.isfinite(calibration_scores)
        split_radii = np.asarray(jnp.stack([
            conformal.split_radius(calibration_scores[k], valid[k], alpha)
            for k in range(horizon)]))
        result["split_calibration_scores"] = int(valid[0].sum())
    covered, counted, radii = np.zeros(horizon), np.zeros(horizon), np.zeros(horizon)
    for scores, mask, issued in scored[calibrating:]:
        if split_radii is not None:
            issued = np.broadcast_to(split_radii, issued.shape)
        covered += np.sum(mask & (scores <= issued), axis=0)
        counted += np.sum(mask, axis=0)
        radii += np.sum(np.where(mask, issued, 0.0), axis=0)
    result.update(scores=counted.astype(int).tolist(),
                  coverage=(covered / np.maximum(counted, 1)).tolist(),
                  radius=(radii / np.maximum(counted, 1)).tolist())
    return result, None if best is None else _snapshot(best, split_radii, horizon)


def format_table(result: dict) -> str:
    """`play`'s result (with model, scene and split) as the command prints it."""
    lines = [f"{result['model']} on {result['scene']} ({result['split']} split, "
             f"{result['frames']} frames, the first {result['calibration_frames']} calibrating): "
             f"{result['method']}, alpha {result['alpha']}",
             "  step     s  coverage  radius (m)  scores"]
    for k, (c, r, n) in enumerate(zip(result["coverage"], result["radius"], result["scores"])):
        lines.append(f"  {k + 1:4d} {(k + 1) * result['step_s']:5.2f}  {c:8.3f}  {r:10.3f}  "
                     f"{n:6d}")
    return "\n".join(lines)


def _histories(player: Stream, ids: np.ndarray) -> np.ndarray:
    """(L, T, 2) the observed steps of these tracks, NaN where not detected."""
    state = player.state
    slots = [int(np.flatnonzero(np.asarray(state.track_ids) == i)[0]) for i in ids]
    positions = np.asarray(state.positions)[slots]
    return np.where(np.asarray(state.detected)[slots][..., None] > 0, positions, np.nan)


def _snapshot(best, split_radii, horizon: int) -> Snapshot:
    _, index, frames_of_file, out, history = best
    truth = np.full(out.futures.shape, np.nan)
    for k, (_, ids, xy) in enumerate(frames_of_file[index + 1:index + 1 + horizon]):
        for row, track in enumerate(out.ids):
            found = np.flatnonzero(ids == track)
            if len(found):
                truth[row, k] = xy[found[0]]
    radii = out.radii if split_radii is None else np.broadcast_to(split_radii, out.radii.shape)
    return Snapshot(frames_of_file[index][0], history, out.futures, radii, truth)


def scene_streams(data_config: DataConfig, split: str, grid) -> list[Iterator[FrameRows]]:
    """The frames of every file of a scene (or of your own data) that the split's windows
    cover, one iterator per file."""
    return [frames(tracks, first, last)
            for tracks, first, last in data.split_frames(data_config, split, grid)]
