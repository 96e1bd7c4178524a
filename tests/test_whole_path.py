"""Whole-path regions (gst_jax.conformal.whole_path_region) and the exact binomial interval
of their joint coverage: the jitted code equals its plain-numpy reference
(gst_jax/testing/conformal_reference.py) in float64; on exchangeable synthetic paths the
regions hold whole paths at their level and within the split-conformal upper bound, where
per-step discs at the same level do not; the Clopper-Pearson interval equals scipy's."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import conformal
from gst_jax.testing import conformal_reference as reference

ALPHA = 0.1
HORIZON = 12
CALIBRATION, FIT, TEST, REPETITIONS = 1000, 500, 1000, 200
Z = 4.0                   # standard errors allowed: a false alarm about once in 30,000 runs


def assert_same(actual, expected):
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    np.testing.assert_array_equal(np.isinf(actual), np.isinf(expected))
    np.testing.assert_array_equal(np.sign(actual[np.isinf(actual)]),
                                  np.sign(expected[np.isinf(expected)]))
    finite = np.isfinite(expected)
    np.testing.assert_allclose(actual[finite], expected[finite], rtol=1e-12, atol=1e-12)


def walks(seed: int, repetitions: int, paths: int, horizon: int = HORIZON):
    """Scores (R, paths, P) and masks of exchangeable paths: the distance from the origin
    (the prediction: standing still) of a 2-d Gaussian random walk whose step scale changes
    with the horizon step (0.04, 0.08, 0.12, 0.16 m, again), times a per-path factor
    (log-normal, sd 0.25: heteroscedastic paths); one path in five is observed only up to a
    random step (at least the first)."""
    rng = np.random.default_rng(seed)
    scale = 0.04 * (1 + np.arange(horizon) % 4)
    factor = rng.lognormal(0.0, 0.25, (repetitions, paths, 1, 1))
    steps = rng.normal(size=(repetitions, paths, horizon, 2)) * scale[:, None] * factor
    scores = np.linalg.norm(np.cumsum(steps, axis=2), axis=-1)
    until = np.where(rng.random((repetitions, paths)) < 0.2,
                     rng.integers(1, horizon, (repetitions, paths)), horizon)
    return scores, np.arange(horizon) < until[..., None]


# (i) the jitted code equals the reference --------------------------------------------------


@pytest.mark.parametrize("paths, alpha, fit_share, scale_level",
                         [(60, 0.1, 0.5, None), (40, 0.2, 0.3, 0.5), (19, 0.1, 0.5, None),
                          (8, 0.1, 0.5, None), (200, 0.05, 0.5, 1.0)])
def test_whole_path_region_equals_reference(paths, alpha, fit_share, scale_level):
    """Random scores with missing steps, paths with none, a step D1 never saw (the last),
    ties (rounded scores) and, for 8 paths, too few of D2 for the level (q = +inf); for 19,
    just enough (10 of D2, the 10th smallest)."""
    rng = np.random.default_rng(paths)
    with jax.enable_x64(True):
        scores = np.round(rng.exponential(1.0, (paths, 6)) * np.arange(1, 7), 1)
        mask = rng.random(scores.shape) < 0.8
        mask[: paths // 10] = False                                  # paths with no step
        fit = rng.random(paths) < fit_share
        mask[fit, -1] = False                                        # D1 never saw step 6
        region = jax.jit(conformal.whole_path_region, static_argnames=("alpha", "scale_level"))(
            scores, mask, alpha=alpha, fit=fit, scale_level=scale_level)
        expected = reference.whole_path_region(scores, mask, alpha, fit=fit,
                                               scale_level=scale_level)
        assert_same(region.scales, expected["scales"])
        assert_same(region.quantile, expected["quantile"])
        assert_same(region.radii, expected["radii"])
        assert int(region.count) == expected["count"]
        assert_same(conformal.path_scores(scores, mask, region.scales), expected["scores"])
        assert np.isinf(region.scales[-1]) and np.isinf(region.radii[-1])
        too_few = math.ceil((int(region.count) + 1) * (1 - alpha)) > int(region.count)
        assert np.isinf(region.quantile) == too_few and too_few == (paths == 8)
        finite = np.where(np.isfinite(region.radii), region.radii, 1.0)
        np.testing.assert_array_equal(conformal.paths_inside(scores, mask, finite),
                                      reference.paths_inside(scores, mask, finite))


def test_given_scales_calibrate_on_every_path_not_marked_fit():
    rng = np.random.default_rng(1)
    with jax.enable_x64(True):
        scores, mask = rng.exponential(1.0, (50, 4)), rng.random((50, 4)) < 0.9
        scales = np.array([0.5, 1.0, 2.0, 4.0])
        region = conformal.whole_path_region(scores, mask, 0.1, scales=scales)
        expected = reference.whole_path_region(scores, mask, 0.1, scales=scales)
        assert_same(region.radii, expected["radii"])
        assert int(region.count) == expected["count"] == int(mask.any(axis=1).sum())
        fit = np.arange(50) < 10
        region = conformal.whole_path_region(scores, mask, 0.1, fit=fit, scales=scales)
        assert_same(region.radii, reference.whole_path_region(scores, mask, 0.1, fit=fit,
                                                              scales=scales)["radii"])


def test_vmap_over_repetitions_equals_a_loop():
    scores, mask = walks(2, 3, 100)
    fit = np.arange(100) < 50
    batched = jax.jit(jax.vmap(lambda s, m: conformal.whole_path_region(s, m, 0.1, fit=fit)))
    regions = batched(scores, mask)
    for r in range(3):
        one = conformal.whole_path_region(scores[r], mask[r], 0.1, fit=fit)
        np.testing.assert_array_equal(regions.radii[r], one.radii)


def test_the_same_paths_may_not_choose_the_scales_and_calibrate_q():
    scores = np.ones((10, 3))
    with pytest.raises(ValueError, match="fit"):
        conformal.whole_path_region(scores, None, 0.1)
    for alpha in (0.0, 1.0, float("nan")):
        with pytest.raises(ValueError, match="alpha"):
            conformal.whole_path_region(scores, None, alpha, scales=np.ones(3))
    with pytest.raises(ValueError, match="scale_level"):
        conformal.whole_path_region(scores, None, 0.1, fit=np.ones(10, bool), scale_level=0.0)
    with pytest.raises(ValueError, match="shape"):
        conformal.whole_path_region(scores[0], None, 0.1, scales=np.ones(3))


# (ii), (iii) coverage on exchangeable synthetic paths ----------------------------------------


@pytest.fixture(scope="module")
def coverage():
    """R = 200 repetitions, each 1000 calibration paths (500 fit the scales, 500 calibrate q)
    and 1000 test paths; per repetition the joint coverage of the whole-path regions, of
    per-step split-conformal discs at alpha (all 1000 calibration paths), and of per-step
    discs at alpha / P (the union bound), and the sum of each one's radii."""
    scores, mask = walks(3, REPETITIONS, CALIBRATION + TEST)
    calibration, test = (scores[:, :CALIBRATION], mask[:, :CALIBRATION]), \
        (scores[:, CALIBRATION:], mask[:, CALIBRATION:])
    fit = np.arange(CALIBRATION) < FIT
    whole = jax.vmap(lambda s, m: conformal.whole_path_region(s, m, ALPHA, fit=fit).radii)
    per_step = jax.vmap(jax.vmap(conformal.split_radius, (1, 1, None)), (0, 0, None))
    radii = {"whole path": jax.jit(whole)(*calibration),
             "per step": jax.jit(per_step, static_argnums=2)(*calibration, ALPHA),
             "union bound": jax.jit(per_step, static_argnums=2)(*calibration, ALPHA / HORIZON)}
    inside = jax.jit(jax.vmap(conformal.paths_inside))
    return {name: (np.asarray(inside(*test, r)).mean(axis=1), np.asarray(r).sum(axis=1))
            for name, r in radii.items()}


def split_conformal_coverage(n: int, alpha: float, test: int) -> tuple[float, float]:
    """Split conformal with n continuous exchangeable scores: the coverage given the
    calibration is Beta(l, n + 1 - l), l = ceil((n+1)(1-alpha)); a repetition measures it
    on `test` paths (binomial). Returns the mean coverage l/(n+1) and the standard deviation
    of one repetition's measured coverage."""
    rank = math.ceil((n + 1) * (1 - alpha))
    mean = rank / (n + 1)
    spread = rank * (n + 1 - rank) / ((n + 1) ** 2 * (n + 2))                  # Var(C)
    sampling = (mean - (spread + mean ** 2)) / test                         # E[C(1-C)]/m
    return mean, math.sqrt(spread + sampling)


def test_whole_path_regions_cover_at_their_level_within_the_upper_bound(coverage):
    """Averaged over 200 repetitions, the joint coverage lies in [1 - alpha, 1 - alpha +
    1/(n+1)] (n = 500 paths calibrate q), within Z standard errors of the mean, the
    standard error from split conformal's law (Beta given the calibration, binomial over
    the test paths); it is also within Z of the exact mean l/(n+1)."""
    covered, _ = coverage["whole path"]
    n = CALIBRATION - FIT
    mean, spread = split_conformal_coverage(n, ALPHA, TEST)
    error = spread / math.sqrt(REPETITIONS)
    measured = covered.mean()
    print(f"whole-path joint coverage {measured:.4f} (exact mean {mean:.4f}, bounds "
          f"[{1 - ALPHA}, {1 - ALPHA + 1 / (n + 1):.4f}], standard error {error:.4f}; "
          f"sd per repetition {covered.std():.4f}, predicted {spread:.4f})")
    assert measured >= 1 - ALPHA - Z * error
    assert measured <= 1 - ALPHA + 1 / (n + 1) + Z * error
    assert abs(measured - mean) <= Z * error
    # the repetitions spread as split conformal's law says (within a quarter)
    assert 0.75 * spread <= covered.std() <= 1.25 * spread


def test_per_step_discs_at_the_same_level_do_not_hold_whole_paths(coverage):
    """Per-step split-conformal discs at alpha cover each step at 1 - alpha but whole paths
    far less often; the union bound (alpha / P a step) holds them with larger radii than the
    whole-path regions'. The standard errors are those measured over the repetitions."""
    per_step, _ = coverage["per step"]
    error = per_step.std() / math.sqrt(REPETITIONS)
    print(f"per-step discs' joint coverage {per_step.mean():.4f} +- {error:.4f}")
    assert per_step.mean() + Z * error < 1 - ALPHA
    (_, whole_size), (union, union_size) = coverage["whole path"], coverage["union bound"]
    print(f"union bound's joint coverage {union.mean():.4f}, its radii summed "
          f"{union_size.mean():.3f} m against the whole-path regions' {whole_size.mean():.3f} m")
    assert union.mean() - Z * union.std() / math.sqrt(REPETITIONS) > 1 - ALPHA
    assert union_size.mean() > whole_size.mean()


# (iv) the exact binomial interval ----------------------------------------------------------


def test_clopper_pearson_equals_scipy():
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(4)
    cases = [(0, 1), (1, 1), (0, 10), (10, 10), (5, 10), (3, 7), (900, 1000), (999, 1000),
             (1, 1000), (0, 100_000), (90_000, 100_000)]
    cases += [(int(rng.integers(0, n + 1)), int(n)) for n in rng.integers(1, 3000, 60)]
    for k, n in cases:
        for confidence in (0.95, 0.9, 0.99):
            lower, upper = conformal.clopper_pearson(k, n, confidence)
            expected = stats.binomtest(k, n).proportion_ci(confidence_level=confidence,
                                                           method="exact")
            assert abs(lower - expected.low) <= 1e-9 and abs(upper - expected.high) <= 1e-9, \
                (k, n, confidence, lower, upper, expected)


def test_joint_coverage_counts_the_present_paths():
    inside = np.array([True, True, False, True, False, True])
    present = np.array([True, True, True, True, False, False])
    report = conformal.joint_coverage(inside, present)
    assert (report.covered, report.paths, report.fraction) == (3, 4, 0.75)
    assert (report.lower, report.upper) == conformal.clopper_pearson(3, 4, 0.95)
    assert report.confidence == 0.95
    empty = conformal.joint_coverage(np.zeros(0, bool))
    assert empty.paths == 0 and math.isnan(empty.fraction) and \
        (empty.lower, empty.upper) == (0.0, 1.0)
    with pytest.raises(ValueError):
        conformal.clopper_pearson(5, 4)
    with pytest.raises(ValueError):
        conformal.clopper_pearson(1, 4, confidence=1.0)


def test_whole_path_radii_are_metres_per_step_and_scale_with_the_scores():
    """Equivariance: scores times c give radii times c (q is unchanged, the scales scale)."""
    scores, mask = walks(5, 1, 400)
    fit = np.arange(400) < 200
    region = conformal.whole_path_region(scores[0], mask[0], 0.1, fit=fit)
    doubled = conformal.whole_path_region(2 * scores[0], mask[0], 0.1, fit=fit)
    np.testing.assert_allclose(doubled.radii, 2 * region.radii, rtol=1e-6)
    np.testing.assert_allclose(doubled.quantile, region.quantile, rtol=1e-6)
    assert region.radii.shape == (HORIZON,) and bool(jnp.all(jnp.isfinite(region.radii)))
