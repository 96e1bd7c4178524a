"""Predictions as TrajNet++ files: written by us, scored from the file exactly as in memory;
TrajNet++'s Col-I / Col-II; malformed files refused with file:line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gst_jax import metrics
from gst_jax.config import DataConfig
from gst_jax.errors import DataError
from gst_jax.evaluation import evaluate_prediction_file, evaluate_run
from gst_jax.runs import load_model

SAMPLE = Path(__file__).parents[1] / "data" / "samples" / "crowd_10hz.txt"
SAMPLE_DATA = DataConfig(scene="crowd_10hz", data=str(SAMPLE), fps=10, scale=0.01)
SCORES = ("aoe", "aoe_std", "foe", "foe_std", "min_ade", "min_fde", "kde_nll", "collision_rate",
          "truth_collision_rate", "col_i", "col_ii", "cv_aoe", "cv_foe", "pedestrians")


@pytest.fixture(scope="module")
def written(tmp_path_factory) -> Path:
    """hotel_d's 3 samples of the sample file's test windows, written by the command."""
    path = tmp_path_factory.mktemp("predictions") / "hotel_d.ndjson"
    result = subprocess.run(
        [sys.executable, "-m", "gst_jax.predict", "pretrained:hotel_d", "--data", str(SAMPLE),
         "--fps", "10", "--units", "cm", "--samples", "3", "--seed", "7", "--out", str(path)],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    return path


def test_a_written_file_scores_exactly_as_the_in_memory_evaluation(written):
    from_file = evaluate_prediction_file(written, SAMPLE_DATA, "test")
    in_memory = evaluate_run(load_model("pretrained:hotel_d"), SAMPLE_DATA, "test",
                             num_samples=3, seed=7)
    assert from_file["samples"] == 3 and from_file["windows"] == in_memory["windows"]
    for name in SCORES:
        assert from_file[name] == pytest.approx(in_memory[name], rel=1e-9, abs=1e-12), name
    assert in_memory["pedestrians"] > 0 and in_memory["col_ii"] > 0    # not a vacuous match


def test_the_file_is_trajnet_ndjson(written):
    rows = [json.loads(line) for line in written.read_text().splitlines()]
    scenes = [row["scene"] for row in rows if "scene" in row]
    predicted = [row["track"] for row in rows if "prediction_number" in row.get("track", {})]
    assert [scene["id"] for scene in scenes] == list(range(len(scenes)))
    assert {track["prediction_number"] for track in predicted} == {0, 1, 2}
    first = scenes[0]
    # 10 Hz frame ids: the 12 predicted steps lie 4 ids apart after the 8 observed.
    frames = sorted({t["f"] for t in predicted if t["scene_id"] == 0})
    assert frames == [first["s"] + 4 * step for step in range(8, 20)] and frames[-1] == first["e"]


def _edited(written: Path, tmp_path: Path, edit) -> Path:
    lines = written.read_text().splitlines()
    edit(lines)
    path = tmp_path / "edited.ndjson"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_malformed_prediction_files_are_refused_with_their_line(written, tmp_path):
    def wrong_scene(lines):
        lines[0] = lines[0].replace('"s": ', '"s": 1')
    with pytest.raises(DataError, match=r"edited.ndjson:1: scene 0 covers frames .* were the "
                                        r"predictions made for this data and split"):
        evaluate_prediction_file(_edited(written, tmp_path, wrong_scene), SAMPLE_DATA, "test")

    line = next(i for i, text in enumerate(written.read_text().splitlines())
                if "prediction_number" in text)

    def text_coordinate(lines):
        row = json.loads(lines[line])
        row["track"]["x"] = "1.5"
        lines[line] = json.dumps(row)
    with pytest.raises(DataError, match=rf"edited.ndjson:{line + 1}: x must be a finite number"):
        evaluate_prediction_file(_edited(written, tmp_path, text_coordinate), SAMPLE_DATA, "test")

    def one_sample_missing(lines):
        del lines[line]
    with pytest.raises(DataError, match="is scored .* lacks some of its 3 x 12 predicted"):
        evaluate_prediction_file(_edited(written, tmp_path, one_sample_missing), SAMPLE_DATA,
                                 "test")


def _two_walkers(gap: float, cross_between_steps: bool = False) -> np.ndarray:
    """(1, 1, 3, 2, 2): walker 0 along y = 0, walker 1 along y = gap; or crossing walker 0's
    path only half-way between two steps."""
    x = np.arange(3.0)
    path0 = np.stack([x, np.zeros(3)], -1)
    path1 = np.stack([x, np.full(3, gap)], -1)
    if cross_between_steps:        # meets walker 0 at (1.5, 0) half-way from step 1 to 2
        path1 = np.array([[3.0, 1.0], [2.0, 1.0], [1.0, -1.0]])
    return np.stack([path0, path1], axis=1)[None, None]


def _scored(pred, truth, primary, predicted, truth_steps) -> metrics.Scored:
    return metrics.Scored(pred=pred, truth=truth, scored_mask=primary, predicted_mask=predicted,
                          truth_step_mask=truth_steps, observed=truth[:, :2],
                          observed_node_mask=truth_steps[:, :2])


@pytest.mark.parametrize("gap, collides", [(0.19, True), (0.2, True), (0.25, False)])
def test_col_i_counts_discs_of_radius_0_1_that_touch(gap, collides):
    pred = _two_walkers(gap)
    everyone = np.ones((1, 2))
    sums = metrics.trajnet_collisions(_scored(pred, pred[0], everyone, everyone,
                                              np.ones((1, 3, 2))))
    assert sums["col_i"].count == 2
    assert list(sums["col_i"].total) == [2.0 if collides else 0.0]
    assert list(sums["col_ii"].total) == [2.0 if collides else 0.0]


def test_col_ii_checks_midpoints_and_skips_segments_without_truth():
    pred = _two_walkers(5.0)
    truth = _two_walkers(0.0, cross_between_steps=True)[0]
    primary = np.array([[1.0, 0.0]])                        # walker 0 is the primary
    seen = np.ones((1, 3, 2))
    sums = metrics.trajnet_collisions(_scored(pred, truth, primary, np.ones((1, 2)), seen))
    assert list(sums["col_i"].total) == [0.0] and list(sums["col_ii"].total) == [1.0]
    seen[0, 2, 1] = 0                                       # walker 1's truth ends at step 1
    sums = metrics.trajnet_collisions(_scored(pred, truth, primary, np.ones((1, 2)), seen))
    assert list(sums["col_ii"].total) == [0.0]
