"""Paired comparisons of two settings over the same episodes (issue 90): McNemar's exact test
and paired-bootstrap intervals, held against hand-worked tables and scipy."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from gst_jax.paired import excludes_zero, mcnemar_exact, paired_means, paired_rates


def outcomes(both: int, only_a: int, only_b: int, neither: int) -> tuple[np.ndarray, np.ndarray]:
    """Two settings' successes over the same episodes, from a 2x2 table."""
    a = [1] * both + [1] * only_a + [0] * only_b + [0] * neither
    b = [1] * both + [0] * only_a + [1] * only_b + [0] * neither
    return np.array(a, bool), np.array(b, bool)


def test_mcnemars_exact_p_from_hand_worked_tables():
    # 5 discordant episodes, all a's: 2 x (1/2)^5.
    assert mcnemar_exact(5, 0) == 2 / 32
    # 10 against 2 of 12: 2 x (C(12,0) + C(12,1) + C(12,2)) / 2^12 = 158 / 4096.
    assert mcnemar_exact(10, 2) == 158 / 4096
    assert mcnemar_exact(0, 0) == 1.0 and mcnemar_exact(3, 3) == 1.0
    for only_a, only_b in [(10, 2), (40, 19), (7, 30)]:
        exact = stats.binomtest(min(only_a, only_b), only_a + only_b, 0.5).pvalue
        assert math.isclose(mcnemar_exact(only_a, only_b), exact, rel_tol=1e-12)


def test_paired_rates_count_only_the_discordant_episodes():
    a, b = outcomes(both=420, only_a=40, only_b=10, neither=30)
    compared = paired_rates(a, b)
    assert (compared["only_a"], compared["only_b"], compared["units"]) == (40, 10, 500)
    assert compared["difference"] == pytest.approx(0.06)
    # The paired normal interval by hand: var = (40 + 10) / 500 - 0.06^2, se = sqrt(var / 500).
    half = 1.96 * math.sqrt((50 / 500 - 0.06 ** 2) / 500)
    assert compared["low"] == pytest.approx(0.06 - half, abs=0.004)
    assert compared["high"] == pytest.approx(0.06 + half, abs=0.004)
    assert excludes_zero(compared) and compared["p"] < 1e-4
    # Swapping the settings mirrors everything.
    swapped = paired_rates(b, a)
    assert swapped["difference"] == pytest.approx(-0.06)
    assert swapped["low"] == pytest.approx(-compared["high"], abs=1e-9)


def test_identical_settings_differ_by_nothing():
    a, _ = outcomes(both=90, only_a=0, only_b=0, neither=10)
    compared = paired_rates(a, a)
    assert (compared["difference"], compared["low"], compared["high"], compared["p"]) == (
        0.0, 0.0, 0.0, 1.0)
    assert not excludes_zero(compared)


def test_a_small_discordance_is_not_called_a_difference():
    a, b = outcomes(both=450, only_a=6, only_b=2, neither=42)
    compared = paired_rates(a, b)
    assert compared["low"] < 0 < compared["high"] and not excludes_zero(compared)
    assert compared["p"] == pytest.approx(stats.binomtest(2, 8, 0.5).pvalue)


def test_paired_means_leave_out_units_either_lacks():
    a = np.array([10.0, 12.0, np.nan, 11.0, 15.0])
    b = np.array([9.0, 11.0, 30.0, np.nan, 13.0])
    compared = paired_means(a, b)
    assert compared["units"] == 3 and compared["difference"] == pytest.approx(4 / 3)
    assert 1.0 <= compared["low"] <= 4 / 3 <= compared["high"] <= 2.0
    with pytest.raises(ValueError, match="same units"):
        paired_means(a, b[:4])
