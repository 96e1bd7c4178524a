"""Where does a learned predictor beat constant velocity? Per-pedestrian errors of a model,
constant velocity and a linear regression on the same pedestrians, binned by how non-linear
the true future is and by what a planner can see during the observation.

Every scored pedestrian (fully detected, as in the paper's metrics) of an evaluation's
windows gives one record (`pedestrian_records`): its ADE / FDE under the model (the mean over
the K samples, so that the average over pedestrians is the paper's AOE / FOE), under constant
velocity (`metrics.constant_velocity`) and under the linear regression (`linear_regression`:
least squares of position on time over the observed steps, extrapolated, as in the S-GAN
tables), and three features:

- `nonlinearity`: the distance between the true endpoint and the constant-velocity
  extrapolation (metres): how far the future leaves a straight line at the last speed;
- `closest`: the closest distance to another detected pedestrian over the observed steps
  (metres; inf when alone), known to a planner at run time;
- `neighbours`: the most people within 2 m at one observed step, known at run time too.

`stratify` bins the records by a feature at fixed edges (chosen before looking at any
result) and gives per bin the count, the mean errors and the paired difference of the model
from each baseline with its 95 % interval (mean +- 1.96 standard errors over pedestrians).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from gst_jax import metrics
from gst_jax.prediction_files import PredictedBatch

NEIGHBOURHOOD_M = 2.0
# Bin edges, fixed before any result was looked at (metres, metres, people).
EDGES = {"nonlinearity": (0.0, 0.5, 1.5, np.inf),
         "closest": (0.0, 1.0, 2.0, 4.0, np.inf),
         "neighbours": (0, 1, 2, 4, np.inf)}
PREDICTORS = ("model", "cv", "linear")


def linear_regression(obs_positions: np.ndarray, obs_node_mask: np.ndarray, *,
                      pred_len: int) -> np.ndarray:
    """Least squares of x and y on the step index over each pedestrian's detected observed
    steps, extrapolated to the next `pred_len` steps. (B, T, N, 2), (B, T, N) -> (B, P, N, 2);
    a pedestrian detected at fewer than two steps stays where it was last seen (or at 0)."""
    positions = np.asarray(obs_positions, np.float64)
    weight = np.asarray(obs_node_mask, np.float64)[..., None]               # (B, T, N, 1)
    steps = np.arange(positions.shape[1], dtype=np.float64)[None, :, None, None]
    count = weight.sum(axis=1)                                               # (B, N, 1)
    mean_t = (weight * steps).sum(axis=1) / np.maximum(count, 1)
    mean_x = (weight * positions).sum(axis=1) / np.maximum(count, 1)         # (B, N, 2)
    centred_t = steps - mean_t[:, None]
    spread = (weight * centred_t ** 2).sum(axis=1)
    slope = (weight * centred_t * (positions - mean_x[:, None])).sum(axis=1)
    slope = np.where(spread > 0, slope / np.where(spread > 0, spread, 1), 0.0)
    future = np.arange(positions.shape[1], positions.shape[1] + pred_len, dtype=np.float64)
    return mean_x[:, None] + (future[None, :, None, None] - mean_t[:, None]) * slope[:, None]


def observed_features(obs_positions: np.ndarray, obs_node_mask: np.ndarray
                      ) -> dict[str, np.ndarray]:
    """closest (B, N): the smallest distance to another detected pedestrian at one observed
    step (inf when never anyone); neighbours (B, N): the most others within 2 m at one step."""
    positions = np.asarray(obs_positions, np.float64)
    detected = np.asarray(obs_node_mask) > 0                                  # (B, T, N)
    apart = np.linalg.norm(positions[:, :, :, None] - positions[:, :, None], axis=-1)
    pair = detected[:, :, :, None] & detected[:, :, None, :]
    pair &= ~np.eye(detected.shape[-1], dtype=bool)
    apart = np.where(pair, apart, np.inf)                                    # (B, T, N, N)
    return {"closest": apart.min(axis=(1, 3)),
            "neighbours": (apart <= NEIGHBOURHOOD_M).sum(axis=3).max(axis=1)}


def pedestrian_records(predicted: Iterable[PredictedBatch], obs_len: int
                       ) -> dict[str, np.ndarray]:
    """One entry per scored pedestrian: `<predictor>_ade` / `<predictor>_fde` for the model
    (mean over its K samples), cv and linear, the features, and `window` (the window's index
    in the order of the batches)."""
    columns: dict[str, list[np.ndarray]] = {}
    windows = 0
    for batch, pred, _ in predicted:
        truth = np.asarray(batch.positions[:, obs_len:], np.float64)          # (B, P, N, 2)
        observed = np.asarray(batch.positions[:, :obs_len])
        observed_mask = np.asarray(batch.node_mask[:, :obs_len])
        pred_len = truth.shape[1]
        futures = {
            "model": np.asarray(pred, np.float64),                             # (K, B, P, N, 2)
            "cv": metrics.constant_velocity(observed, observed_mask, pred_len=pred_len)[None],
            "linear": linear_regression(observed, observed_mask, pred_len=pred_len)[None]}
        scored = (np.asarray(batch.fully_detected_mask)
                  * np.asarray(batch.scene_mask)[:, None]) > 0                 # (B, N)
        row = {}
        for name, future in futures.items():
            errors = metrics.offset_errors(future, truth)                      # (K, B, P, N)
            row[f"{name}_ade"] = errors.mean(axis=2).mean(axis=0)
            row[f"{name}_fde"] = errors[:, :, -1].mean(axis=0)
        cv_end = futures["cv"][0, :, -1]
        row["nonlinearity"] = np.linalg.norm(truth[:, -1] - cv_end, axis=-1)
        row.update(observed_features(observed, observed_mask))
        row["window"] = np.broadcast_to(windows + np.arange(scored.shape[0])[:, None],
                                        scored.shape)
        for name, values in row.items():
            columns.setdefault(name, []).append(np.asarray(values)[scored])
        windows += int(np.asarray(batch.scene_mask).sum())
    return {name: np.concatenate(parts) for name, parts in columns.items()}


def paired(difference: np.ndarray) -> dict[str, float]:
    """Mean of paired differences with its 95 % interval (normal, over pedestrians)."""
    n = len(difference)
    mean = float(np.mean(difference)) if n else float("nan")
    half = float(1.96 * np.std(difference, ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
    return {"mean": mean, "low": mean - half, "high": mean + half}


def stratify(records: dict[str, np.ndarray], feature: str,
             edges: tuple[float, ...] | None = None) -> list[dict]:
    """Per bin [edges[i], edges[i + 1]) of `feature`: count, each predictor's mean ADE / FDE,
    and the model's paired differences from cv and from linear (ADE and FDE), with their
    95 % intervals; negative: the model is better."""
    edges = EDGES[feature] if edges is None else edges
    values = records[feature]
    bins = []
    for low, high in zip(edges[:-1], edges[1:]):
        inside = (values >= low) & (values < high)
        row = {"feature": feature, "low": low, "high": high, "count": int(inside.sum())}
        for name in PREDICTORS:
            for error in ("ade", "fde"):
                column = records[f"{name}_{error}"][inside]
                row[f"{name}_{error}"] = float(column.mean()) if len(column) else float("nan")
        for baseline in ("cv", "linear"):
            for error in ("ade", "fde"):
                row[f"model_minus_{baseline}_{error}"] = paired(
                    records[f"model_{error}"][inside] - records[f"{baseline}_{error}"][inside])
        bins.append(row)
    return bins
