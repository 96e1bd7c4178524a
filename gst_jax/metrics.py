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


def release_spread_sums(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> dict:
    """The release's "std" (its scripts/eval.py; docs/MODEL.md 4), as sums over windows: per
    window, the standard deviation (ddof 1, torch's default) across the K runs of the
    window's summed AOE (or FOE). Divided by the pedestrian count, it is the release's figure.

    pred (K, B, P, N, 2), truth (B, P, N, 2), mask (B, N) ->
    {"aoe_window_std_sum": (), "foe_window_std_sum": ()}.
    """
    errors = offset_errors(pred, truth)
    mask = np.asarray(mask, np.float64)
    ddof = 1 if pred.shape[0] > 1 else 0
    per_window = {name: np.sum(np.where(mask > 0, value * mask, 0.0), axis=-1)     # (K, B)
                  for name, value in (("aoe", errors.mean(axis=2)), ("foe", errors[:, :, -1]))}
    return {f"{name}_window_std_sum": np.sum(np.std(value, axis=0, ddof=ddof))
            for name, value in per_window.items()}


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


# TrajNet++ (Kothari et al. 2021): a pedestrian is a disc of radius 0.1 m; two collide when
# their discs touch at a step or half-way between consecutive steps.
TRAJNET_PERSON_RADIUS = 0.1


def trajnet_collision_sums(pred: np.ndarray, truth: np.ndarray, primary_mask: np.ndarray,
                           predicted_mask: np.ndarray, truth_step_mask: np.ndarray) -> dict:
    """TrajNet++'s Col-I and Col-II with every pedestrian of `primary_mask` as primary in turn.

    Col-I: the primary's predicted path meets another pedestrian's predicted path (same
    sample); Col-II: it meets another pedestrian's ground truth, over the segments whose both
    ends exist. TrajNet++ interpolates each segment at 2 parts (its ends and its midpoint).
    pred (K, B, P, N, 2), truth (B, P, N, 2), primary_mask / predicted_mask (B, N),
    truth_step_mask (B, P, N) -> {"col1_sum": (K,), "col2_sum": (K,), "count": ()}.
    """
    pred = np.nan_to_num(np.asarray(pred, np.float64))
    truth = np.asarray(truth, np.float64)
    primary = np.asarray(primary_mask) > 0
    others = ~np.eye(primary.shape[-1], dtype=bool)

    def points(paths):                      # (..., P, N, 2) -> (..., 2P - 1, N, 2)
        midpoints = (paths[..., 1:, :, :] + paths[..., :-1, :, :]) / 2
        return np.concatenate([paths, midpoints], axis=-3)

    def meets(neighbour_paths, neighbour_valid):
        """(K, B, N) whether each primary's predicted path meets any valid neighbour's."""
        # (K, B, 2P - 1, N, N): primary n against neighbour m at every point.
        gap = np.linalg.norm(points(pred)[..., :, None, :]
                             - points(neighbour_paths)[..., None, :, :], axis=-1)
        touching = (gap <= 2 * TRAJNET_PERSON_RADIUS) & neighbour_valid[..., None, :] & others
        return np.any(touching, axis=(-3, -1)) & primary

    valid = np.asarray(truth_step_mask) > 0                             # (B, P, N)
    segment_valid = valid[:, 1:] & valid[:, :-1]
    truth_valid = np.concatenate([valid, segment_valid], axis=1)        # (B, 2P-1, N)
    predicted = np.asarray(predicted_mask) > 0
    predicted_valid = np.broadcast_to(predicted[:, None], truth_valid.shape)
    return {"col1_sum": meets(pred, predicted_valid).sum(axis=(1, 2)).astype(float),
            "col2_sum": meets(truth, truth_valid).sum(axis=(1, 2)).astype(float),
            "count": float(primary.sum())}


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
