"""Trajectory metrics (docs/MODEL.md 4), numpy only, as sums so batches can be accumulated.

Shapes: K samples, B scenes, P predicted steps, N pedestrian slots. `mask` (B, N) selects the
pedestrians evaluated (fully detected, real scenes).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

# Trajectron++ clips the log density of the truth below at this value.
KDE_LOG_DENSITY_FLOOR = -20.0
# Two pedestrians closer than this (metres) at the same step collide.
COLLISION_DISTANCE = 0.1


def fully_detected_mask(node_mask: np.ndarray) -> np.ndarray:
    """1 for pedestrians valid at every step.  (B, T, N) -> (B, N)."""
    return np.min(np.asarray(node_mask), axis=-2)


def offset_errors(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Euclidean distance per sample, scene, step and pedestrian.  -> (K, B, P, N)."""
    return np.linalg.norm(np.asarray(pred) - np.asarray(truth)[None], axis=-1)


def aoe_foe_sums(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Per sample (run) k, the sums over pedestrians of AOE (mean over steps) and FOE (last step).

    pred (K, B, P, N, 2), truth (B, P, N, 2), mask (B, N) ->
    {"aoe_sum": (K,), "foe_sum": (K,), "count": ()}.
    """
    errors = offset_errors(pred, truth)
    mask = np.asarray(mask, np.float64)
    # Pedestrians outside the mask may have no prediction (NaN): they add exactly nothing.
    return {"aoe_sum": np.sum(np.where(mask > 0, errors.mean(axis=2) * mask, 0.0), axis=(1, 2)),
            "foe_sum": np.sum(np.where(mask > 0, errors[:, :, -1] * mask, 0.0), axis=(1, 2)),
            "count": np.sum(mask)}


def min_ade_fde_sums(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Best-of-K: per pedestrian the smallest ADE and (independently) the smallest FDE, summed."""
    errors = offset_errors(pred, truth)
    mask = np.asarray(mask, np.float64)
    return {"min_ade_sum": np.sum(np.where(mask > 0, errors.mean(axis=2).min(axis=0) * mask, 0.0)),
            "min_fde_sum": np.sum(np.where(mask > 0, errors[:, :, -1].min(axis=0) * mask, 0.0))}


def kde_log_density(samples: np.ndarray, point: np.ndarray) -> float:
    """log density at `point` (2,) of scipy's Gaussian KDE (Scott bandwidth) over samples (K, 2).

    Samples that span less than a plane (all equal, or collinear: GST (D) often samples the
    same graph K times) have no density off their support: the log density is the floor.
    """
    try:
        log_density = float(stats.gaussian_kde(samples.T).logpdf(point)[0])
    except np.linalg.LinAlgError:
        return KDE_LOG_DENSITY_FLOOR
    return max(log_density, KDE_LOG_DENSITY_FLOOR) if np.isfinite(log_density) else KDE_LOG_DENSITY_FLOOR


def kde_nll_sums(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """Trajectron++ KDE NLL: per pedestrian, minus the mean over steps of the clipped log density.

    -> {"nll_sum": (), "count": ()} summed over the pedestrians in `mask`.
    """
    pred, truth = np.asarray(pred, np.float64), np.asarray(truth, np.float64)
    total, count = 0.0, 0
    for b, n in zip(*np.nonzero(np.asarray(mask) > 0)):
        steps = [kde_log_density(pred[:, b, t, n], truth[b, t, n]) for t in range(pred.shape[2])]
        total -= float(np.mean(steps))
        count += 1
    return {"nll_sum": total, "count": count}


def collision_sums(positions: np.ndarray, mask: np.ndarray,
                   step_mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of pedestrians closer than 0.1 m at any step, and pairs considered.

    positions (..., B, P, N, 2) (leading sample axes allowed), mask (B, N) pedestrians in
    play, step_mask (B, P, N) optional per-step validity (ground truth with gaps).
    Returns (collisions, pairs), each summed over scenes, per leading sample index.
    """
    positions = np.asarray(positions)
    mask = np.asarray(mask) > 0
    distance = np.linalg.norm(positions[..., :, None, :] - positions[..., None, :, :], axis=-1)
    both = mask[:, None, :, None] & mask[:, None, None, :]                      # (B, 1, N, N)
    if step_mask is not None:
        valid = np.asarray(step_mask) > 0
        both = both & valid[..., :, None] & valid[..., None, :]
    upper = np.triu(np.ones(mask.shape[-1:] * 2, bool), k=1)
    close = (distance < COLLISION_DISTANCE) & both & upper
    collided = np.any(close, axis=-3)                                          # over steps
    pairs = np.sum(np.any(both & upper, axis=-3), axis=(-3, -2, -1))
    return np.sum(collided, axis=(-3, -2, -1)).astype(float), np.broadcast_to(
        pairs, collided.shape[:-3]).astype(float)


def constant_velocity(obs_positions: np.ndarray, obs_node_mask: np.ndarray, *,
                      pred_len: int) -> np.ndarray:
    """Constant-velocity baseline: repeat the last observed displacement.

    obs_positions (B, T, N, 2), obs_node_mask (B, T, N) -> (B, P, N, 2); pedestrians without
    a last displacement stay where they were last seen.
    """
    obs_positions = np.asarray(obs_positions)
    velocity = (obs_positions[:, -1] - obs_positions[:, -2]) * np.asarray(obs_node_mask)[:, -1, :, None]
    steps = np.arange(1, pred_len + 1)[None, :, None, None]
    return obs_positions[:, -1][:, None] + steps * velocity[:, None]
