"""Where a model beats constant velocity (gst_jax.strata): the linear-regression baseline, the
observed features and the binning, on hand-built scenes."""

from __future__ import annotations

import numpy as np
import pytest

from gst_jax import metrics, strata
from gst_jax.data.batch import SceneBatch, node_mask_from_positions
from gst_jax.prediction_files import PredictedBatch

OBS, PRED = 8, 12


def test_the_linear_regression_continues_a_straight_walk_and_fits_a_noisy_one():
    t = np.arange(OBS, dtype=float)
    walk = np.stack([0.4 * t + 1.0, -0.2 * t], -1)[None, :, None]            # (1, T, 1, 2)
    future = strata.linear_regression(walk, np.ones((1, OBS, 1)), pred_len=PRED)
    k = np.arange(OBS, OBS + PRED, dtype=float)
    np.testing.assert_allclose(future[0, :, 0], np.stack([0.4 * k + 1.0, -0.2 * k], -1))
    # Alternating noise of +-0.1 m on x: the last step looks half as fast (0.2 m), so constant
    # velocity ends 2.5 m short (0.1 m of noise, then 12 x 0.2 m); least squares over the eight
    # steps ends 0.15 m off.
    noisy = walk + np.array([0.1, 0.0]) * (-1.0) ** t[None, :, None, None]
    fitted = strata.linear_regression(noisy, np.ones((1, OBS, 1)), pred_len=PRED)
    cv = metrics.constant_velocity(noisy, np.ones((1, OBS, 1)), pred_len=PRED)
    assert abs(fitted[0, -1, 0, 0] - (0.4 * k[-1] + 1.0)) < 0.2
    assert abs(cv[0, -1, 0, 0] - (0.4 * k[-1] + 1.0)) == pytest.approx(2.5)


def test_the_regression_uses_the_detected_steps_only_and_keeps_a_lone_detection_in_place():
    t = np.arange(OBS, dtype=float)
    positions = np.zeros((1, OBS, 2, 2))
    positions[0, :, 0, 0] = 0.5 * t
    mask = np.ones((1, OBS, 2))
    mask[0, :3, 0] = 0
    positions[0, :3, 0] = 99.0                     # not detected there: must not count
    mask[0, :, 1] = 0
    mask[0, 5, 1] = 1
    positions[0, 5, 1] = (2.0, 3.0)
    future = strata.linear_regression(positions, mask, pred_len=2)
    np.testing.assert_allclose(future[0, :, 0, 0], [4.0, 4.5])
    np.testing.assert_allclose(future[0, :, 1], [[2.0, 3.0], [2.0, 3.0]])


def test_observed_features_take_the_closest_pass_and_the_most_neighbours_within_2_m():
    """Three people: A and B pass 0.5 m apart at one step; C is 1.5 m from A at every step
    but detected only at two; nobody else."""
    positions = np.zeros((1, OBS, 3, 2))
    positions[0, :, 1] = (3.0, 0.0)
    positions[0, 4, 1] = (0.5, 0.0)
    positions[0, :, 2] = (0.0, 1.5)
    mask = np.ones((1, OBS, 3))
    mask[0, :6, 2] = 0
    features = strata.observed_features(positions, mask)
    np.testing.assert_allclose(features["closest"][0], [0.5, 0.5, 1.5])
    # At step 4 A has B (0.5 m) within 2 m; at steps 6-7 A has C (1.5 m), B (3 m) not.
    assert features["neighbours"][0].tolist() == [1, 1, 1]
    alone = strata.observed_features(positions[:, :, :1], mask[:, :, :1])
    assert np.isinf(alone["closest"][0, 0]) and alone["neighbours"][0, 0] == 0


def _scene(velocities, turn_at_end=0.0):
    """One window of people walking straight at `velocities` (N, 2) per step, the last
    predicted step displaced by `turn_at_end` metres in y (a non-linear future)."""
    t = np.arange(OBS + PRED, dtype=float)[:, None, None]
    positions = np.asarray(velocities, float)[None] * t + np.arange(len(velocities))[None, :,
                                                                                        None]
    positions[-1, :, 1] += turn_at_end
    mask = np.ones(positions.shape[:2], np.float32)
    return SceneBatch(positions=positions[None].astype(np.float32), position_mask=mask[None],
                      node_mask=node_mask_from_positions(mask[None]),
                      scene_mask=np.ones(1, np.float32), window_index=np.zeros(1, np.int32))


def test_records_pair_the_models_errors_with_both_baselines_on_the_same_pedestrians():
    batch = _scene([[0.5, 0.0], [0.0, 0.3]], turn_at_end=1.0)
    truth = np.asarray(batch.positions[0, OBS:])
    samples = np.stack([truth, truth + np.array([0.2, 0.0])])[:, None]      # (K, B, P, N, 2)
    records = strata.pedestrian_records([PredictedBatch(batch, samples, np.ones((1, 2)))], OBS)
    assert len(records["model_ade"]) == 2
    np.testing.assert_allclose(records["model_ade"], 0.1, rtol=1e-5)       # mean of 0, 0.2
    np.testing.assert_allclose(records["cv_fde"], 1.0, rtol=1e-5)          # the turn at the end
    np.testing.assert_allclose(records["linear_fde"], 1.0, rtol=1e-5)
    np.testing.assert_allclose(records["cv_ade"], 1.0 / PRED, rtol=1e-5)
    np.testing.assert_allclose(records["nonlinearity"], 1.0, rtol=1e-5)
    assert records["window"].tolist() == [0, 0]


def test_stratify_counts_each_pedestrian_once_with_paired_intervals():
    rng = np.random.default_rng(0)
    n = 400
    records = {"nonlinearity": rng.uniform(0, 3, n), "cv_ade": rng.uniform(0.2, 1.0, n)}
    records["cv_fde"] = 2 * records["cv_ade"]
    records["linear_ade"], records["linear_fde"] = records["cv_ade"], records["cv_fde"]
    # The model gains 0.1 m where the future bends by 1.5 m or more, nothing elsewhere.
    gain = np.where(records["nonlinearity"] >= 1.5, 0.1, 0.0)
    records["model_ade"] = records["cv_ade"] - gain
    records["model_fde"] = records["cv_fde"] - gain
    bins = strata.stratify(records, "nonlinearity")
    assert sum(b["count"] for b in bins) == n
    assert [b["low"] for b in bins] == [0.0, 0.5, 1.5]
    assert bins[-1]["model_minus_cv_ade"]["mean"] == pytest.approx(-0.1)
    assert bins[0]["model_minus_cv_ade"]["mean"] == pytest.approx(0.0)
    noisy = dict(records, model_ade=records["model_ade"] + rng.normal(0, 0.05, n))
    cell = strata.stratify(noisy, "nonlinearity")[-1]["model_minus_cv_ade"]
    assert cell["low"] < -0.1 < cell["high"] < 0


def test_the_fallback_rule_is_fixed_on_the_finished_held_out_runs_and_picks_per_person(tmp_path):
    """experiments/fallback.py: only finished paper-val runs (a summary.json) fix the rule, and
    on two people whom the observed features tell apart (GST better for the one close to
    another person, CV for the one alone) the chosen rule gives each the better prediction;
    a rule is chosen only where it beats both predictors alone."""
    from fallback import CV_ALONE, choose, difference, held_out_models
    for scene, finished in (("eth", True), ("hotel", False)):
        (tmp_path / scene).mkdir()
        if finished:
            (tmp_path / scene / "summary.json").write_text("{}")
    assert held_out_models(tmp_path) == {"eth": str(tmp_path / "eth")}
    people = {"model_ade": np.array([0.2, 0.9]), "cv_ade": np.array([0.5, 0.4]),
              "closest": np.array([0.6, 5.0]), "neighbours": np.array([3, 0])}
    best, scores = choose({"eth": people})
    assert scores[best] == pytest.approx(0.3)                  # (0.2 + 0.4) / 2
    # Where GST is worse for everyone, CV alone is chosen: the rules that give GST to
    # nobody tie with it, and it is listed first.
    assert choose({"eth": dict(people, model_ade=people["model_ade"] + 1)})[0] == CV_ALONE
    # Paired against CV: -0.3 and 0 per person; two scenes alike halve the interval's
    # variance on their mean.
    gain = difference({"eth": people, "hotel": people}, best, "cv_ade")
    half = 1.96 * np.std([-0.3, 0.0], ddof=1) / np.sqrt(2)
    assert gain["eth"]["mean"] == gain["average"]["mean"] == pytest.approx(-0.15)
    assert gain["eth"]["high"] == pytest.approx(-0.15 + half)
    assert gain["average"]["high"] == pytest.approx(-0.15 + half / np.sqrt(2))
