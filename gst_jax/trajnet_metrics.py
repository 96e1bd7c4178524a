"""TrajNet++'s own figures of a submission, as its evaluator computes them (numpy only).

trajnetplusplusbaselines' evaluator (`evaluator/trajnet_evaluator.py`, with
trajnetplusplustools 0.3.0's metrics) pairs the i-th scene row of the prediction file with
the i-th of the ground truth, checks that the primary's predicted frames (sample 0) are the
truth's last 12 ("frame numbers are not consistent" otherwise) and scores each scene by its
primary alone; every figure is averaged over the N scenes:

- ADE / FDE: sample 0's mean and final distance to the truth.
- Top-3 ADE / FDE (K >= 3): of samples 0-2, the one of least ADE: its ADE and its FDE, not
  the least FDE (gst_jax's minFDE is the least over samples, independently of ADE).
  Top-K ADE / FDE: the same rule over all K samples.
- Col-I: the scenes (% of N, every scene counted) where the primary's sample 0 meets a
  predicted neighbour's sample 0. Defined only where every scene predicts as many neighbours
  as TrajNet++ counts (everyone with a row before the first predicted row; its table prints
  -1 otherwise).
- Col-II: the scenes (% of N) where the primary's sample 0 meets a neighbour's true path
  (those same neighbours).
- NLL (K >= 50): the mean log-likelihood of the truth, per step, under a Gaussian KDE of the
  first 50 samples (scipy's, clipped below at -20), averaged over the steps whose samples
  span a plane: a log-likelihood, higher is better, the opposite sign of gst_jax's KDE NLL.

Beside them, constant velocity's ADE / FDE on the same primaries (their last observed
displacement repeated), as gst_jax's evaluation gives it on its pedestrians.

Two paths meet (`paths_meet`) when, over their common frames taken in order, the discs of
radius 0.1 m around them touch at a pair of consecutive frames or half-way between.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from gst_jax.data.trajnet import OBSERVED_ROWS, SceneSet
from gst_jax.errors import DataError
from gst_jax.metrics import KDE_LOG_DENSITY_FLOOR, kde_log_densities_where_defined
from gst_jax.prediction_files import PredictionFile

__all__ = ["NLL_SAMPLES", "TOP_K", "log_likelihood", "paths_meet", "score_submission"]

# TrajNet++'s evaluator: top-k over samples 0 to TOP_K - 1 (its "Top3"), NLL over the first
# NLL_SAMPLES samples (it passes n_samples=50; trajnetplusplustools' own default is 100).
TOP_K = 3
NLL_SAMPLES = 50
# trajnetplusplustools.metrics.collision: people are discs of this radius.
PERSON_RADIUS = 0.1
# trajnetplusplustools.metrics.nll skips a step whose log density exceeds this.
LOG_DENSITY_CEILING = 100.0


def paths_meet(frames_a: np.ndarray, xy_a: np.ndarray, frames_b: np.ndarray,
               xy_b: np.ndarray) -> bool:
    """trajnetplusplustools.metrics.collision: paths (F_a,), (F_a, 2) and (F_b,), (F_b, 2),
    each one row a frame in frame order, meet over their common frames."""
    common = np.intersect1d(frames_a, frames_b)
    a, b = xy_a[np.isin(frames_a, common)], xy_b[np.isin(frames_b, common)]
    if len(common) < 2:
        return False
    gaps = []
    for start, end in ((a[:-1], b[:-1]), (a[1:], b[1:])):          # each segment's ends
        gaps.append(start - end)
    # np.linspace's midpoint: start + (end - start) / 2.
    gaps.append((a[:-1] + (a[1:] - a[:-1]) / 2) - (b[:-1] + (b[1:] - b[:-1]) / 2))
    distance = np.stack([np.sqrt(g[:, 0] * g[:, 0] + g[:, 1] * g[:, 1]) for g in gaps])
    return bool(np.any(distance.min(axis=0) <= 2 * PERSON_RADIUS))


def log_likelihood(samples: np.ndarray, truth: np.ndarray) -> float | None:
    """trajnetplusplustools.metrics.nll of one scene: samples (S, P, 2), truth (P, 2) -> the
    mean over steps of the clipped log density of the truth; None where no step counts (its
    "All Predictions are Identical")."""
    log_density, defined = kde_log_densities_where_defined(samples, truth)
    clipped = np.maximum(log_density, KDE_LOG_DENSITY_FLOOR)
    counted = defined & (clipped <= LOG_DENSITY_CEILING)
    return float(np.mean(clipped[counted])) if counted.any() else None


def score_submission(file: PredictionFile, scene_set: SceneSet) -> dict[str, Any]:
    """TrajNet++'s figures of a submission `file` for the scenes of `scene_set` (module
    docstring), paired and checked as its evaluator pairs them: a `DataError` names the first
    scene it would refuse."""
    _check_pairing(file, scene_set)
    by_scene = _rows_by_scene(file)
    num_samples = file.num_samples
    sums = {name: 0.0 for name in ("ade", "fde", "top3_ade", "top3_fde", "topk_ade", "topk_fde",
                                   "col_i", "col_ii", "log_likelihood", "cv_ade", "cv_fde")}
    short_scenes, identical_scenes = 0, 0
    for index, scene in enumerate(scene_set.scenes):
        frames = scene_set.frames(index)
        truth_paths = _truth_paths(scene_set, index)
        predicted_frames = frames[OBSERVED_ROWS:]
        primary_truth = truth_paths[scene.primary][1][-len(predicted_frames):]
        observed = truth_paths[scene.primary][1][OBSERVED_ROWS - 2:OBSERVED_ROWS]
        steps = np.arange(1, len(predicted_frames) + 1)[:, None]
        constant_velocity = observed[1] + steps * (observed[1] - observed[0])
        cv_errors = np.linalg.norm(constant_velocity - primary_truth, axis=-1)
        sums["cv_ade"] += cv_errors.mean()
        sums["cv_fde"] += cv_errors[-1]
        rows = by_scene.get(scene.scene_id, {})
        primary = _samples(file, scene.scene_id, scene.primary, rows.get(scene.primary, {}),
                           predicted_frames)                                   # (K, P, 2)
        errors = np.linalg.norm(primary - primary_truth, axis=-1)             # (K, P)
        ades, fdes = errors.mean(axis=1), errors[:, -1]
        sums["ade"] += ades[0]
        sums["fde"] += fdes[0]
        for name, count in (("top3", TOP_K), ("topk", num_samples)):
            best = int(np.argmin(ades[:count]))
            sums[f"{name}_ade"] += ades[best]
            sums[f"{name}_fde"] += fdes[best]
        neighbours = [p for p, (path_frames, _) in truth_paths.items()
                      if p != scene.primary and path_frames[0] < predicted_frames[0]]
        sums["col_ii"] += any(paths_meet(predicted_frames, primary[0], *truth_paths[p])
                              for p in neighbours)
        predicted = [p for p in rows if p != scene.primary]
        if len(predicted) != len(neighbours):
            short_scenes += 1
        sums["col_i"] += any(paths_meet(predicted_frames, primary[0], *_sample_zero(rows[p]))
                             for p in predicted)
        if num_samples >= NLL_SAMPLES:
            scene_likelihood = log_likelihood(primary[:NLL_SAMPLES], primary_truth)
            identical_scenes += scene_likelihood is None
            sums["log_likelihood"] += scene_likelihood or 0.0
    count = len(scene_set)
    mean = {name: float(total / count) for name, total in sums.items()}
    return {
        "scenes": count, "samples": num_samples,
        "ade": mean["ade"], "fde": mean["fde"],
        "top3_ade": mean["top3_ade"] if num_samples >= TOP_K else None,
        "top3_fde": mean["top3_fde"] if num_samples >= TOP_K else None,
        "topk_ade": mean["topk_ade"], "topk_fde": mean["topk_fde"],
        "col_i_percent": None if short_scenes else 100 * mean["col_i"],
        "col_i_undefined_scenes": short_scenes,
        "col_ii_percent": 100 * mean["col_ii"],
        "log_likelihood": (mean["log_likelihood"]
                           if num_samples >= NLL_SAMPLES and not identical_scenes else None),
        "log_likelihood_samples": NLL_SAMPLES,
        "log_likelihood_undefined_scenes": identical_scenes,
        "cv_ade": mean["cv_ade"], "cv_fde": mean["cv_fde"],
    }


def _check_pairing(file: PredictionFile, scene_set: SceneSet) -> None:
    """Scene row i of the file must be scene i of the data: id, primary and frames."""
    for index, scene in enumerate(scene_set.scenes):
        if index >= len(file.scene_rows):
            raise DataError(f"{file.path}: {len(file.scene_rows)} scene rows, the data's split "
                            f"{len(scene_set)} scenes: TrajNet++'s evaluator pairs them in "
                            "order, scene for scene")
        line, scene_id, primary, _, _ = file.scene_rows[index]
        if (scene_id, primary) != (scene.scene_id, scene.primary):
            raise DataError(f"{file.path}:{line}: scene row {index + 1} is scene {scene_id} "
                            f"(primary {primary}), the data's scene {index + 1} is scene "
                            f"{scene.scene_id} (primary {scene.primary}): TrajNet++'s "
                            "evaluator pairs the two files' scenes in order")
    if len(file.scene_rows) > len(scene_set):
        line = file.scene_rows[len(scene_set)][0]
        raise DataError(f"{file.path}:{line}: more scene rows than the data's split has scenes "
                        f"({len(scene_set)})")


def _rows_by_scene(file: PredictionFile) -> dict[int, dict[int, dict[tuple[int, int], Any]]]:
    """scene id -> pedestrian -> (frame, sample) -> (x, y), the rows within the scene's frames
    (its evaluator reads no other)."""
    frames = {scene_id: (first, last) for (_, scene_id, _, first, last) in file.scene_rows}
    by_scene: dict[int, dict[int, dict[tuple[int, int], Any]]] = {}
    for (scene_id, pedestrian, frame, k), xy in file.samples.items():
        first, last = frames.get(scene_id, (frame + 1, frame))
        if first <= frame <= last:
            by_scene.setdefault(scene_id, {}).setdefault(pedestrian, {})[frame, k] = xy
    return by_scene


def _samples(file: PredictionFile, scene_id: int, pedestrian: int,
             rows: dict[tuple[int, int], Any], frames: np.ndarray) -> np.ndarray:
    """(K, P, 2) the primary's samples at the predicted frames; each must be there."""
    samples = np.empty((file.num_samples, len(frames), 2))
    for k in range(file.num_samples):
        for t, frame in enumerate(frames):
            if (int(frame), k) not in rows:
                stop = (' (its evaluator stops here: "frame numbers are not consistent")'
                        if k == 0 else "")
                raise DataError(f"{file.path}: scene {scene_id}: its primary {pedestrian} has "
                                f"no prediction {k} at frame {int(frame)}, one of the frames "
                                f"TrajNet++ scores{stop}")
            samples[k, t] = rows[int(frame), k]
    return samples


def _sample_zero(rows: dict[tuple[int, int], Any]) -> tuple[np.ndarray, np.ndarray]:
    """(F,) frames and (F, 2) positions of sample 0, in frame order."""
    frames = sorted(frame for frame, k in rows if k == 0)
    return np.array(frames, np.int64), np.array([rows[f, 0] for f in frames], float).reshape(-1, 2)


def _truth_paths(scene_set: SceneSet, index: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """pedestrian -> (frames, positions) of everyone with a row in scene `index`'s frames."""
    tracks, scene = scene_set.tracks, scene_set.scenes[index]
    lo, hi = np.searchsorted(tracks.frames, [scene.start, scene.end + 1])
    frames, pedestrians, xy = tracks.frames[lo:hi], tracks.pedestrians[lo:hi], tracks.xy[lo:hi]
    return {int(p): (frames[pedestrians == p], xy[pedestrians == p])
            for p in np.unique(pedestrians)}
