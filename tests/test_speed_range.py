"""experiments/speed_range.py: straight walkers, their scores, the rule and the range; one
shipped model measured at two speeds (one compile)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gst_jax import pretrained
from gst_jax.config import TimeGrid
from gst_jax.predictors import GST
from speed_range import errors, measure, speed_range, straight_walkers, within

GRID = TimeGrid(step_s=0.5, obs_len=3, pred_len=4)
RESULTS = Path(__file__).parents[1] / "results" / "speed_range.json"


def test_straight_walkers_walk_their_speed_abreast():
    histories, truth, direction = straight_walkers((1.0, 2.0), GRID, 3)
    assert histories.shape == (16, 3, 3, 2) and truth.shape == (16, 3, 4, 2)
    # Scene 8 + 2: 2 m/s heading 90 degrees (north), 1 m per 0.5 s step.
    np.testing.assert_allclose(direction[10], [0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(truth[10, 1], [[0, 1], [0, 2], [0, 3], [0, 4]], atol=1e-12)
    np.testing.assert_allclose(histories[10, 1], [[0, -2], [0, -1], [0, 0]], atol=1e-12)
    # The row: 0.8 m apart across the walk (west to east), the same steps.
    np.testing.assert_allclose(histories[10, :, -1], [[0.8, 0], [0, 0], [-0.8, 0]], atol=1e-12)


def walker_predicted(*futures) -> dict:
    """Scores of one walker heading east at 1 m/s from the origin, 4 steps of 1 m predicted
    as `futures`."""
    truth = np.array([[[[1.0, 0], [2, 0], [3, 0], [4, 0]]]])
    return errors(np.array([[futures]], dtype=float), truth, np.zeros((1, 1, 2)),
                  np.array([[1.0, 0.0]]))


def test_the_rule_passes_a_good_prediction_and_flags_wrong_ones():
    exact = walker_predicted([1, 0], [2, 0], [3, 0], [4, 0])
    slow = walker_predicted([0.8, 0], [1.6, 0], [2.4, 0], [3.2, 0])       # 80 % of the speed
    slower = walker_predicted([0.7, 0], [1.4, 0], [2.1, 0], [2.8, 0])     # 70 %
    backwards = walker_predicted([-1, 0], [-2, 0], [-3, 0], [-4, 0])
    turning = walker_predicted([1, 0], [2, 0], [3, 0], [3.5, 0.5])       # last step 45 degrees
    assert [float(within(s)[0, 0]) for s in (exact, slow, slower, backwards, turning)] == [
        1, 1, 0, 0, 0]
    np.testing.assert_allclose([s["fde_share"][0, 0] for s in (exact, slow, backwards)],
                               [0.0, 0.2, 2.0], atol=1e-12)
    np.testing.assert_allclose([s["speed_ratio"][0, 0] for s in (exact, slow, backwards)],
                               [1.0, 0.8, -1.0], atol=1e-12)
    np.testing.assert_allclose([s["heading_error_deg"][0, 0] for s in (backwards, turning)],
                               [180.0, 45.0], atol=1e-9)
    # The turning walker ends 0.71 m from the truth, 18 % of the 4 m walked: its heading fails.
    assert turning["fde_share"][0, 0] < 0.25


def test_the_range_is_the_longest_run_of_passing_speeds():
    speeds = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5]
    assert speed_range(speeds, [True, True, False, True, True, True, False]) == {
        "low": 2.0, "high": 3.0, "also": [0.5, 1.0]}
    assert speed_range(speeds, [True, True, False, True, True, False, True]) == {
        "low": 0.5, "high": 1.0, "also": [2.0, 2.5, 3.5]}               # the slower on a tie
    assert speed_range(speeds, [False] * 7) == {"low": None, "high": None, "also": []}
    assert speed_range(speeds, [True] * 7) == {"low": 0.5, "high": 3.5, "also": []}


def test_a_planner_model_predicts_its_training_speed_and_not_a_sprint():
    """crowdnav_sim trained on simulated humans walking 0.5 to 1.5 m/s: a lone walker at
    1.25 m/s passes in every direction, one at 6 m/s does not (it is predicted far too slow),
    as published in results/speed_range.json."""
    config, params = pretrained.load_pretrained("crowdnav_sim")
    alone = measure(GST(config), params, config.grid, speeds=(1.25, 6.0),
                    cases={"alone": 1})["cases"]["alone"]
    assert alone["passed"] == [True, False]
    assert alone["speed_ratio_max"][1] < 0.75 and alone["worst_fde_share"][1] > 0.25
    assert 0.75 < alone["speed_ratio_min"][0] <= alone["speed_ratio_max"][0] < 1.25
    published = json.loads(RESULTS.read_text())["models"]["crowdnav_sim"]
    at = [published["speeds"].index(speed) for speed in (1.25, 6.0)]
    for field in ("worst_fde_share", "worst_heading_error_deg", "speed_ratio_min"):
        np.testing.assert_allclose(alone[field], [published["cases"]["alone"][field][i]
                                                  for i in at], atol=2e-3, err_msg=field)
