"""Metrics on hand-built predictions whose values are computed by hand."""

from __future__ import annotations

import numpy as np
import pytest

from gst_jax import metrics
from gst_jax.config import DataConfig
from gst_jax.data import pad_windows
from gst_jax.data.windows import Window
from gst_jax.evaluation import protocol_line, score
from gst_jax.prediction_files import PredictedBatch

P = 4


def scored(pred: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> metrics.Scored:
    """pred (K, B, P, N, 2) against truth (B, P, N, 2), scoring the pedestrians of mask (B, N)."""
    steps = np.ones(truth.shape[:-1])
    return metrics.Scored(pred=pred, truth=truth, scored_mask=mask, predicted_mask=mask,
                          truth_step_mask=steps, observed=truth[:, :2],
                          observed_node_mask=steps[:, :2])


def straight_away(speeds):
    """(K, 1, P, 1, 2): sample k moves along x at speeds[k] m/step from the origin."""
    steps = np.arange(1, P + 1)
    return np.stack([np.stack([s * steps, 0 * steps], -1) for s in speeds])[:, None, :, None, :]


def test_aoe_foe_min_ade_fde_by_hand():
    truth = np.zeros((1, P, 1, 2))
    pred = straight_away([1.0, 0.5])          # errors t+1 and (t+1)/2 at step t
    mask = np.ones((1, 1))
    sums = metrics.aoe_foe(scored(pred, truth, mask))
    np.testing.assert_allclose(sums["aoe"].total, [2.5, 1.25])    # mean(1, 2, 3, 4) = 2.5
    np.testing.assert_allclose(sums["foe"].total, [4.0, 2.0])
    assert sums["aoe"].count == 1
    best = metrics.min_ade_fde(scored(pred, truth, mask))
    assert best["min_ade"].total == pytest.approx(1.25)
    assert best["min_fde"].total == pytest.approx(2.0)
    assert metrics.aoe_foe(scored(pred, truth, np.zeros((1, 1))))["aoe"].count == 0
    # Per-run values report their mean over runs and, as `_std`, their spread.
    summary = metrics.summarize(sums)
    assert summary["aoe"] == pytest.approx(1.875) and summary["aoe_std"] == pytest.approx(0.625)


def test_release_spread_is_the_per_window_std_of_summed_errors_over_pedestrians():
    # Two windows, three runs. Window 0: one pedestrian at speeds 1, 0.5, 0 (AOE 2.5, 1.25,
    # 0); window 1: two pedestrians, each at 1 in run 0 only (summed AOE 5, 0, 0).
    truth = np.zeros((2, P, 2, 2))
    first, second = straight_away([1.0, 0.5, 0.0]), straight_away([1.0, 0.0, 0.0])
    pred = np.concatenate([np.concatenate([first, first * np.nan], axis=3),
                           np.concatenate([second, second], axis=3)], axis=1)
    mask = np.array([[1.0, 0.0], [1.0, 1.0]])
    sums = metrics.release_spread(scored(pred, truth, mask))
    # torch's std (ddof 1): std(2.5, 1.25, 0) = 1.25, std(5, 0, 0) = 5 / sqrt(3).
    assert sums["release_aoe_std"].total == pytest.approx(1.25 + 5 / np.sqrt(3))
    assert sums["release_foe_std"].total == pytest.approx(2.0 + 8 / np.sqrt(3))
    assert sums["release_aoe_std"].count == 3


def test_kde_nll_matches_the_gaussian_kde_formula():
    rng = np.random.default_rng(0)
    samples = rng.normal(size=(20, 2)) * [0.3, 0.1] + [1.0, 2.0]
    point = np.array([1.1, 1.9])
    # Scott's rule in 2-D: bandwidth factor K^(-1/6) times the sample covariance.
    covariance = np.cov(samples.T) * len(samples) ** (-2 / 6)
    inverse, det = np.linalg.inv(covariance), np.linalg.det(covariance)
    diffs = point - samples
    kernels = (np.exp(-0.5 * np.einsum("ki,ij,kj->k", diffs, inverse, diffs))
               / (2 * np.pi * np.sqrt(det)))
    expected = np.log(kernels.mean())
    densities = metrics.kde_log_densities(
        np.stack([samples, samples, np.ones((20, 2))], axis=1),
        np.stack([point, point + 100, point]))
    assert densities[0] == pytest.approx(expected, rel=1e-6)
    # Far from all samples the log density is clipped at -20.
    assert densities[1] == metrics.KDE_LOG_DENSITY_FLOOR
    # Identical samples (GST (D) drawing one graph K times) have no density: the floor.
    assert densities[2] == metrics.KDE_LOG_DENSITY_FLOOR

    pred = np.broadcast_to(samples[:, None, None, None, :], (20, 1, P, 1, 2))
    truth = np.broadcast_to(point, (1, P, 1, 2))
    sums = metrics.kde_nll(scored(pred, truth, np.ones((1, 1))))
    assert sums["kde_nll"].count == 1
    assert sums["kde_nll"].total == pytest.approx(-expected, rel=1e-6)
    assert metrics.kde_nll(scored(pred[:2], truth, np.ones((1, 1)))) == {}   # K = 2: no KDE


def test_kde_log_densities_are_scipys_gaussian_kde_point_by_point():
    """All groups at once, against scipy.stats.gaussian_kde one group at a time: clouds of
    3, 4 and 20 samples, round, stretched and slanted, at points near and far, and samples
    that span no plane (identical, or on a line: scipy's Cholesky factorisation fails)."""
    from scipy.stats import gaussian_kde

    rng = np.random.default_rng(1)
    for k in (3, 4, 20):
        samples = rng.normal(size=(k, 300, 2)) * rng.uniform(0.01, 2.0, size=(300, 2))
        samples[..., 1] += rng.uniform(-3.0, 3.0, size=300) * samples[..., 0]
        points = (samples.mean(axis=0) + rng.normal(size=(300, 2)) * samples.std(axis=0)
                  * rng.uniform(0.1, 5.0, size=(300, 1)))
        samples[:, 0] = [1.5, -2.0]
        samples[:, 1] = np.linspace(0.0, 1.0, k)[:, None] * [1.0, 0.5] + [3.0, 1.0]
        expected = []
        for group in range(samples.shape[1]):
            try:
                value = float(gaussian_kde(samples[:, group].T).logpdf(points[group])[0])
            except np.linalg.LinAlgError:
                value = -np.inf
            expected.append(max(value, metrics.KDE_LOG_DENSITY_FLOOR)
                            if np.isfinite(value) else metrics.KDE_LOG_DENSITY_FLOOR)
        densities = metrics.kde_log_densities(samples, points)
        np.testing.assert_allclose(densities, expected, rtol=1e-9, atol=1e-9)
        assert densities[0] == densities[1] == metrics.KDE_LOG_DENSITY_FLOOR
        assert np.mean(densities > metrics.KDE_LOG_DENSITY_FLOOR) > 0.5


def test_collisions_count_pairs_closer_than_10_cm():
    positions = np.zeros((1, P, 3, 2))
    positions[0, :, 1, 0] = 1.0                # pedestrian 1 one metre away throughout
    positions[0, :, 2, 0] = [3.0, 2.0, 1.05, 3.0]  # pedestrian 2 passes within 5 cm of 1 at step 2
    collisions, pairs = metrics.collision_sums(positions, np.ones((1, 3)))
    assert (collisions, pairs) == (1.0, 3.0)
    collisions, pairs = metrics.collision_sums(positions, np.array([[1.0, 1.0, 0.0]]))
    assert (collisions, pairs) == (0.0, 1.0)
    step_mask = np.ones((1, P, 3))
    step_mask[0, 2, 2] = 0                     # not observed at the close step
    collisions, _ = metrics.collision_sums(positions, np.ones((1, 3)), step_mask)
    assert collisions == 0.0
    per_sample = metrics.collision_sums(np.stack([positions, positions + [[0.0, 0.0]]]),
                                        np.ones((1, 3)))
    np.testing.assert_array_equal(per_sample[0], [1.0, 1.0])


def test_constant_velocity_repeats_the_last_displacement():
    obs = np.zeros((1, 3, 2, 2))
    obs[0, :, 0] = [[0, 0], [1, 0], [2, 1]]    # last step (1, 1)
    obs[0, :, 1] = [[5, 5], [5, 5], [5, 5]]
    node_mask = np.ones((1, 3, 2))
    future = metrics.constant_velocity(obs, node_mask, pred_len=2)
    np.testing.assert_allclose(future[0, :, 0], [[3, 2], [4, 3]])
    np.testing.assert_allclose(future[0, :, 1], [[5, 5], [5, 5]])
    node_mask[0, 2, 0] = 0                     # no last displacement: stays put
    np.testing.assert_allclose(metrics.constant_velocity(obs, node_mask, pred_len=2)[0, :, 0],
                               [[2, 1], [2, 1]])


def _window(num_pedestrians: int = 2) -> Window:
    """A window of walkers moving 0.4 m per step along x, all detected at every step."""
    steps = np.arange(8 + P, dtype=np.float32)[:, None, None] * [0.4, 0.0]
    positions = steps + np.arange(num_pedestrians)[None, :, None] * [0.0, 1.0]
    return Window(positions.astype(np.float32), np.ones((8 + P, num_pedestrians), np.float32),
                  np.arange(num_pedestrians), "walkers", 0, 1, obs_len=8)


def test_a_new_metric_is_one_function_and_one_line(monkeypatch):
    """A metric registered in METRICS is scored and reported by the evaluation unchanged."""
    def max_error(s: metrics.Scored) -> dict[str, metrics.Ratio]:
        return {"max_error": metrics.Ratio(s.over_scored(s.errors.max(axis=2)), s.count)}
    monkeypatch.setitem(metrics.METRICS, "max_error", max_error)

    batch = pad_windows([_window()], 2)
    truth = batch.positions[:, 8:]
    pred = np.stack([truth + [0.0, 0.3], truth + [0.0, 0.1]])      # 0.3 m off, then 0.1 m
    result = score([PredictedBatch(batch, pred, np.ones((1, 2)))], obs_len=8)
    assert result["max_error"] == pytest.approx(0.2)
    assert result["max_error_std"] == pytest.approx(0.1)
    assert result["aoe"] == pytest.approx(0.2) and result["pedestrians"] == 2
    assert result["cv_aoe"] == pytest.approx(0.0, abs=1e-6)       # walkers at constant velocity


def test_a_prediction_files_protocol_line_claims_no_sampling_it_cannot_know():
    """A model's evaluation drew its samples itself (hard, tau 0.03); a prediction file's were
    drawn by whoever wrote it, so its line says only how many it holds."""
    config = DataConfig(scene="zara1")
    assert protocol_line(config, "test", 20, 200) == (
        "zara1, protocol paper, test split, 20 samples (hard, tau 0.03), 200 epochs")
    from_file = protocol_line(config, "test", 5)
    assert from_file == ("zara1, protocol paper, test split, 5 samples per pedestrian as the "
                         "file holds them")
