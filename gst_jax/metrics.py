"""Trajectory metrics (docs/MODEL.md 4), numpy only, as running sums over batches.

A metric is one function of a `Scored` batch returning `Ratio`s by name, and one line in
`METRICS`; `summarize` turns the summed ratios into the reported figures: a ratio with a
per-run axis (K,) gives its mean over runs and, as `<name>_std`, their spread.

Shapes: K samples (the paper's runs), B scenes, P predicted steps, N pedestrian slots.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import numpy as np

# Trajectron++ clips the log density of the truth below at this value.
KDE_LOG_DENSITY_FLOOR = -20.0
# Two pedestrians whose predicted (or true) positions at the same step are closer than this
# (metres) collide. Not `simulate.ROBOT_COLLISION_DISTANCE`, a robot's clearance.
COLLISION_DISTANCE = 0.1
# TrajNet++ (Kothari et al. 2021): a pedestrian is a disc of radius 0.1 m; two collide when
# their discs touch at a step or half-way between consecutive steps.
TRAJNET_PERSON_RADIUS = 0.1


@dataclasses.dataclass(frozen=True)
class Scored:
    """One batch of sampled futures and what they are scored against (numpy arrays).

    pred: (K, B, P, N, 2) sampled positions, NaN where nobody was predicted; None when only a
      baseline is scored. truth: (B, P, N, 2). scored_mask: (B, N) the pedestrians scored
      (fully detected, real scenes). predicted_mask: (B, N) those predicted. truth_step_mask:
      (B, P, N) where the truth exists. observed, observed_node_mask: (B, T_obs, N, 2) and
      (B, T_obs, N), for baselines.
    """

    pred: np.ndarray | None
    truth: np.ndarray
    scored_mask: np.ndarray
    predicted_mask: np.ndarray
    truth_step_mask: np.ndarray
    observed: np.ndarray
    observed_node_mask: np.ndarray

    @property
    def samples(self) -> np.ndarray:
        """pred, for the metrics of a model's samples (never asked of a baseline's batch)."""
        assert self.pred is not None, "a baseline's batch has no samples"
        return self.pred

    @property
    def errors(self) -> np.ndarray:
        """(K, B, P, N) distance of each sample to the truth."""
        return offset_errors(self.samples, self.truth)

    def over_scored(self, values: np.ndarray) -> np.ndarray:
        """values (..., B, N) summed over the scored pedestrians -> (...). Pedestrians outside
        the mask may have no prediction (NaN): they add exactly nothing."""
        mask = np.asarray(self.scored_mask, np.float64)
        return np.sum(np.where(mask > 0, values * mask, 0.0), axis=(-2, -1))

    @property
    def count(self) -> float:
        return float(np.sum(self.scored_mask))


class Ratio(NamedTuple):
    """A metric's running sums: its value is total / count. total () or (K,) per run."""

    total: np.ndarray | float
    # The field shadows tuple.count (mypy: an incompatible override); the name is every
    # record's, and nothing calls tuple.count on a Ratio.
    count: float  # type: ignore[assignment]


def offset_errors(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Euclidean distance per sample, scene, step and pedestrian.  -> (K, B, P, N)."""
    return np.linalg.norm(np.asarray(pred) - np.asarray(truth)[None], axis=-1)


def aoe_foe(s: Scored) -> dict[str, Ratio]:
    """Per run k: AOE (error averaged over the steps) and FOE (at the last step), averaged
    over the scored pedestrians: the paper's metrics, with their spread over runs."""
    errors = s.errors
    return {"aoe": Ratio(s.over_scored(errors.mean(axis=2)), s.count),
            "foe": Ratio(s.over_scored(errors[:, :, -1]), s.count)}


def min_ade_fde(s: Scored) -> dict[str, Ratio]:
    """Best-of-K: per pedestrian the smallest ADE and (independently) the smallest FDE."""
    errors = s.errors
    return {"min_ade": Ratio(s.over_scored(errors.mean(axis=2).min(axis=0)), s.count),
            "min_fde": Ratio(s.over_scored(errors[:, :, -1].min(axis=0)), s.count)}


def release_spread(s: Scored) -> dict[str, Ratio]:
    """The release's "std" (its scripts/eval.py; docs/MODEL.md 4): per window, the standard
    deviation (ddof 1, torch's default) across the K runs of the window's summed AOE (or FOE),
    summed over windows and divided by the pedestrian count."""
    errors = s.errors
    mask = np.asarray(s.scored_mask, np.float64)
    ddof = 1 if errors.shape[0] > 1 else 0

    def spread(per_pedestrian):                                      # (K, B, N)
        per_window = np.sum(np.where(mask > 0, per_pedestrian * mask, 0.0), axis=-1)
        return Ratio(np.sum(np.std(per_window, axis=0, ddof=ddof)), s.count)

    return {"release_aoe_std": spread(errors.mean(axis=2)),
            "release_foe_std": spread(errors[:, :, -1])}


def kde_log_densities(samples: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(G,) log density at each point (G, 2) of a Gaussian KDE over its samples (K, G, 2), as
    scipy.stats.gaussian_kde computes it (Scott's bandwidth), for all G at once; clipped
    below at KDE_LOG_DENSITY_FLOOR.

    Samples that span less than a plane (all equal, or collinear: GST (D) often samples the
    same graph K times) have no density off their support: the floor, where scipy's Cholesky
    factorisation of their covariance fails.
    """
    log_density, defined = kde_log_densities_where_defined(samples, points)
    return np.where(defined, np.maximum(log_density, KDE_LOG_DENSITY_FLOOR),
                    KDE_LOG_DENSITY_FLOOR)


def kde_log_densities_where_defined(samples: np.ndarray, points: np.ndarray
                                    ) -> tuple[np.ndarray, np.ndarray]:
    """`kde_log_densities` unclipped, and (G,) bool where each is defined: its samples span a
    plane (scipy's Cholesky factorisation succeeds) and it is finite."""
    samples, points = np.asarray(samples, np.float64), np.asarray(points, np.float64)
    k = samples.shape[0]
    # Scott's rule in 2-D: the kernels' covariance is the samples' (ddof 1) times K^(-1/3);
    # scipy scales the covariance's Cholesky factor by K^(-1/6).
    factor = float(k) ** (-1.0 / 6.0)
    deviations = samples - samples.mean(axis=0)
    covariance = np.einsum("kgi,kgj->gij", deviations, deviations) / (k - 1)     # (G, 2, 2)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        # The lower Cholesky factor [[l00, 0], [l10, l11]], scaled by the bandwidth.
        l00 = np.sqrt(covariance[:, 0, 0])
        l10 = covariance[:, 1, 0] / l00
        l11_squared = covariance[:, 1, 1] - l10 * l10
        spans_a_plane = (covariance[:, 0, 0] > 0) & (l11_squared > 0)
        l00, l10, l11 = l00 * factor, l10 * factor, np.sqrt(l11_squared) * factor

        def whitened(v):
            """L^-1 v, v (..., G, 2): samples and points each, as scipy whitens them."""
            first = v[..., 0] / l00
            return np.stack([first, (v[..., 1] - l10 * first) / l11], axis=-1)

        residuals = whitened(points) - whitened(samples)                          # (K, G, 2)
        log_kernels = -0.5 * np.sum(residuals ** 2, axis=-1)                       # (K, G)
        log_norm = -np.log(2 * np.pi) - np.log(l00) - np.log(l11)
        peak = np.max(log_kernels, axis=0)
        log_density = (peak + np.log(np.mean(np.exp(log_kernels - peak), axis=0))
                       + log_norm)
    return log_density, spans_a_plane & np.isfinite(log_density)


def kde_nll(s: Scored) -> dict[str, Ratio]:
    """Trajectron++ KDE NLL: per pedestrian, minus the mean over steps of the clipped log
    density of the truth under the K samples. A 2-D KDE needs more samples than dimensions:
    none with K <= 2."""
    if s.samples.shape[0] <= 2:
        return {}
    scenes, pedestrians = np.nonzero(np.asarray(s.scored_mask) > 0)
    pred = np.asarray(s.samples, np.float64)[:, scenes, :, pedestrians]   # (S, K, P, 2)
    truth = np.asarray(s.truth, np.float64)[scenes, :, pedestrians]    # (S, P, 2)
    log_densities = kde_log_densities(
        np.moveaxis(pred, 1, 0).reshape(pred.shape[1], -1, 2), truth.reshape(-1, 2))
    total = -np.sum(np.mean(log_densities.reshape(truth.shape[:2]), axis=1))
    return {"kde_nll": Ratio(np.float64(total), s.count)}


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



def collision_rates(s: Scored) -> dict[str, Ratio]:
    """Pairs of predicted pedestrians that come closer than COLLISION_DISTANCE, in the
    samples (over all runs) and in the truth."""
    predicted, pairs = collision_sums(s.samples, s.predicted_mask)
    true, true_pairs = collision_sums(s.truth, s.predicted_mask, s.truth_step_mask)
    return {"collision_rate": Ratio(np.sum(predicted), float(np.sum(pairs))),
            "truth_collision_rate": Ratio(true, float(true_pairs))}


def trajnet_collisions_by_primary(pred: np.ndarray, truth: np.ndarray, primary_mask: np.ndarray,
                                  predicted_mask: np.ndarray,
                                  truth_step_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TrajNet++'s Col-I and Col-II with every pedestrian of `primary_mask` as primary in turn.

    Col-I: the primary's predicted path meets another pedestrian's predicted path (same
    sample); Col-II: it meets another pedestrian's ground truth, over the segments whose both
    ends exist. TrajNet++ interpolates each segment at 2 parts (its ends and its midpoint).
    pred (K, B, P, N, 2), truth (B, P, N, 2), primary_mask / predicted_mask (B, N),
    truth_step_mask (B, P, N) -> the primaries meeting others per sample, (K,) each for Col-I
    and Col-II.
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
    return (meets(pred, predicted_valid).sum(axis=(1, 2)).astype(float),
            meets(truth, truth_valid).sum(axis=(1, 2)).astype(float))



def trajnet_collisions(s: Scored) -> dict[str, Ratio]:
    """TrajNet++'s Col-I (against the predicted neighbours) and Col-II (against the true
    ones), every scored pedestrian taken as primary in turn, per run."""
    col_i, col_ii = trajnet_collisions_by_primary(s.samples, s.truth, s.scored_mask,
                                                  s.predicted_mask, s.truth_step_mask)
    return {"col_i": Ratio(col_i, s.count), "col_ii": Ratio(col_ii, s.count)}


def constant_velocity(obs_positions: np.ndarray, obs_node_mask: np.ndarray, *,
                      pred_len: int) -> np.ndarray:
    """Constant-velocity baseline: repeat the last observed displacement.

    obs_positions (B, T, N, 2), obs_node_mask (B, T, N) -> (B, P, N, 2); pedestrians without
    a last displacement stay where they were last seen.
    """
    obs_positions = np.asarray(obs_positions)
    velocity = ((obs_positions[:, -1] - obs_positions[:, -2])
                * np.asarray(obs_node_mask)[:, -1, :, None])
    steps = np.arange(1, pred_len + 1)[None, :, None, None]
    return obs_positions[:, -1][:, None] + steps * velocity[:, None]


def constant_velocity_errors(s: Scored) -> dict[str, Ratio]:
    """AOE / FOE of the constant-velocity baseline on the same pedestrians."""
    future = constant_velocity(s.observed, s.observed_node_mask, pred_len=s.truth.shape[1])
    errors = offset_errors(future[None], s.truth)[0]
    return {"cv_aoe": Ratio(s.over_scored(errors.mean(axis=1)), s.count),
            "cv_foe": Ratio(s.over_scored(errors[:, -1]), s.count)}


# Every metric of an evaluation, in the order of its report.
METRICS: dict[str, Callable[[Scored], dict[str, Ratio]]] = {
    "aoe_foe": aoe_foe,
    "min_ade_fde": min_ade_fde,
    "release_spread": release_spread,
    "kde_nll": kde_nll,
    "collisions": collision_rates,
    "trajnet_collisions": trajnet_collisions,
    "constant_velocity": constant_velocity_errors,
}
# Those that need no model's samples.
BASELINES = ("constant_velocity",)


def accumulate(totals: dict[str, Ratio], ratios: dict[str, Ratio]) -> None:
    """Add one batch's ratios to the running `totals` (in place)."""
    for name, ratio in ratios.items():
        if name in totals:
            ratio = Ratio(totals[name].total + ratio.total, totals[name].count + ratio.count)
        totals[name] = Ratio(np.asarray(ratio.total, np.float64), ratio.count)


def summarize(totals: dict[str, Ratio]) -> dict[str, float]:
    """Each ratio's value; one with a per-run axis: its mean over runs and `<name>_std`."""
    result = {}
    for name, ratio in totals.items():
        value = ratio.total / max(ratio.count, 1.0)
        if np.ndim(value):
            result[name], result[f"{name}_std"] = float(np.mean(value)), float(np.std(value))
        else:
            result[name] = float(value)
    return result
