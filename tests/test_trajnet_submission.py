"""TrajNet++ submissions: `predict` for a TrajNet++ file writes its own scenes, which
trajnetplusplusbaselines' evaluator pairs scene for scene (its frame check passes for every
one), and `evaluate`'s TrajNet++ figures are those its evaluator computes with
trajnetplusplustools' metrics.

The evaluator (github vita-epfl/trajnetplusplusbaselines, evaluator/trajnet_evaluator.py at
99a6e9d) is not on PyPI: `official_figures` replicates its pairing and its sums (without its
per-category tables) around trajnetplusplustools' `Reader` and metrics. The predictions are
constant velocity plus random walks (numpy): the model is not the point, but for one tiny
model's submission, whose compile the last test pays."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest
import trajnetplusplustools as trajnet

from gst_jax import data, metrics
from gst_jax.config import DataConfig, ModelConfig, TimeGrid, TrainConfig
from gst_jax.data.trajnet import load_scenes
from gst_jax.errors import DataError
from gst_jax.evaluate import main as evaluate_main
from gst_jax.evaluation import evaluate_prediction_file, write_run_predictions
from gst_jax.model import init_params
from gst_jax.prediction_files import PredictedBatch, write_scene_predictions
from gst_jax.runs import Run

TRAJNET = data.default_data_dir() / "trajnetpp"
LCAS = DataConfig(scene="lcas")
# WILDTRACK's rows (2 Hz) read 0.4 s apart, one a model step, as TrajNet++'s baselines read
# every file (--fps 12.5: 5 frame ids a row).
WILDTRACK = DataConfig(scene="wildtrack", data=str(TRAJNET / "wildtrack.ndjson"), fps=12.5)
GRID = TimeGrid()
# WILDTRACK as annotated: 2 Hz rows, a model of 0.5 s steps (pretrained:wildtrack_d's grid).
WILDTRACK_2HZ, GRID_2HZ = DataConfig(scene="wildtrack"), TimeGrid(step_s=0.5)
# The evaluator's defaults: 9 observed rows, 12 predicted.
OBS_LENGTH, PRED_LENGTH = 9, 12


def official_figures(truth: Path, predictions: Path) -> dict:
    """trajnetplusplusbaselines' `eval(gt, input_file, args)` for one pair of files: its
    TrajnetEvaluator.aggregate's overall sums, divided as its Metrics.avg_vals divides them;
    `paired`: the scenes whose frame check passed (it raises at the first that fails)."""
    reader_gt = trajnet.Reader(str(truth), scene_type="paths")
    scenes_gt = [scene for _, scene in reader_gt.scenes()]
    scenes_id_gt = [scene_id for scene_id, _ in reader_gt.scenes()]
    reader_pred = trajnet.Reader(str(predictions), scene_type="paths")
    scenes_pred = [scene for _, scene in reader_pred.scenes()]
    num_predictions = 0
    for track in scenes_pred[0][0]:
        if track.prediction_number and track.prediction_number > num_predictions:
            num_predictions = track.prediction_number
    sums = dict.fromkeys(("ade", "fde", "gt_col", "pred_col", "topk_ade", "topk_fde", "nll"),
                         0.0)
    enable_col1, paired = True, 0
    for i in range(len(scenes_gt)):
        ground_truth = scenes_gt[i]
        primary_tracks_all = [t for t in scenes_pred[i][0] if t.scene_id == scenes_id_gt[i]]
        neighbours_tracks_all = [[t for t in scenes_pred[i][j] if t.scene_id == scenes_id_gt[i]]
                                 for j in range(1, len(scenes_pred[i]))]
        neighbours_tracks_all = [track for track in neighbours_tracks_all if len(track)]
        primary_tracks = [t for t in primary_tracks_all if t.prediction_number == 0]
        neighbours_tracks = [[t for t in track if t.prediction_number == 0]
                             for track in neighbours_tracks_all]
        frame_gt = [t.frame for t in ground_truth[0]][-PRED_LENGTH:]
        frame_pred = [t.frame for t in primary_tracks]
        if frame_gt != frame_pred:
            raise AssertionError(f"frame numbers are not consistent (scene {i}): {frame_gt} "
                                 f"against {frame_pred}")
        paired += 1
        sums["ade"] += trajnet.metrics.average_l2(ground_truth[0], primary_tracks,
                                                  n_predictions=PRED_LENGTH)
        sums["fde"] += trajnet.metrics.final_l2(ground_truth[0], primary_tracks)
        obs_end_frame = ground_truth[0][OBS_LENGTH].frame               # drop_post_obs
        ground_truth = [track for track in ground_truth if track[0].frame < obs_end_frame]
        for j in range(1, len(ground_truth)):
            if trajnet.metrics.collision(primary_tracks, ground_truth[j],
                                         n_predictions=PRED_LENGTH):
                sums["gt_col"] += 1
                break
        if len(ground_truth) - 1 != len(neighbours_tracks):
            enable_col1 = False
        if enable_col1:
            for j in range(len(neighbours_tracks)):
                if trajnet.metrics.collision(primary_tracks, neighbours_tracks[j],
                                             n_predictions=PRED_LENGTH):
                    sums["pred_col"] += 1
                    break
        if num_predictions > 1:
            topk_ade, topk_fde = trajnet.metrics.topk(primary_tracks_all, ground_truth[0],
                                                      n_predictions=PRED_LENGTH)
            sums["topk_ade"] += topk_ade
            sums["topk_fde"] += topk_fde
        if num_predictions > 48:
            sums["nll"] += trajnet.metrics.nll(primary_tracks_all, ground_truth[0],
                                               n_predictions=PRED_LENGTH, n_samples=50)
    count = len(scenes_gt)
    return {"scenes": count, "paired": paired, "ade": sums["ade"] / count,
            "fde": sums["fde"] / count, "col_ii_percent": sums["gt_col"] / (0.01 * count),
            "col_i_percent": sums["pred_col"] / (0.01 * count) if enable_col1 else -1,
            "top3_ade": sums["topk_ade"] / count, "top3_fde": sums["topk_fde"] / count,
            "log_likelihood": sums["nll"] / count}


def assert_same_figures(ours: dict, official: dict, samples: int) -> None:
    assert official["paired"] == official["scenes"] == ours["scenes"]
    for name in ("ade", "fde", "col_ii_percent", "top3_ade", "top3_fde"):
        assert ours[name] == pytest.approx(official[name], abs=1e-6), name
    if official["col_i_percent"] == -1:
        assert ours["col_i_percent"] is None and ours["col_i_undefined_scenes"] > 0
    else:
        assert ours["col_i_percent"] == pytest.approx(official["col_i_percent"], abs=1e-6)
    if samples >= 50:
        assert ours["log_likelihood"] == pytest.approx(official["log_likelihood"], abs=1e-6)
    else:
        assert ours["log_likelihood"] is None


def noisy_constant_velocity(window_set: data.WindowSet, samples: int, seed: int = 0,
                            step_m: float = 0.15):
    """K samples of every predicted pedestrian: constant velocity plus a random walk of steps
    `step_m` (the standard deviation of each coordinate's, metres)."""
    rng = np.random.default_rng(seed)
    for batch in data.evaluation_batches(window_set):
        obs = GRID.obs_len
        future = metrics.constant_velocity(batch.positions[:, :obs], batch.node_mask[:, :obs],
                                           pred_len=GRID.pred_len)
        walk = rng.normal(scale=step_m, size=(samples, *future.shape)).cumsum(axis=2)
        predicted = batch.predicted_mask(obs) * batch.scene_mask[:, None]
        positions = np.where(predicted[None, :, None, :, None] > 0, future[None] + walk, np.nan)
        yield PredictedBatch(batch, positions.astype(np.float32), predicted)


def scene_rows(path: Path) -> list[dict]:
    return [json.loads(line)["scene"] for line in path.read_text().splitlines()
            if '"scene"' in line]


def with_scenes(source: Path, scene_ids: list[int], path: Path) -> Path:
    """A copy of TrajNet++ file `source` holding only the scene rows of `scene_ids` (in its
    order) and every track row: the ground truth of those scenes."""
    wanted = set(scene_ids)
    lines = [line for line in source.read_text().splitlines()
             if '"scene"' not in line or json.loads(line)["scene"]["id"] in wanted]
    path.write_text("\n".join(lines) + "\n")
    return path


# WILDTRACK at --fps 12.5, TrajNet++'s baselines' reading, is paired in the Col-I test below.
@pytest.mark.parametrize("config, grid", [(LCAS, GRID), (WILDTRACK_2HZ, GRID_2HZ)],
                         ids=["lcas", "wildtrack-2hz"])
def test_a_submission_for_the_test_scenes_is_paired_and_scored_as_trajnet_does(config, grid,
                                                                             tmp_path):
    source = TRAJNET / f"{config.scene}.ndjson"
    # The test split's scenes: those within the frames of its windows, in the file's order.
    (_, first, last), = data.split_frames(config, "test", grid)
    expected = [row["id"] for row in scene_rows(source)
                if first <= row["s"] and row["e"] <= last]
    scene_set = load_scenes(config, "test", grid)
    submission = tmp_path / "submission.ndjson"
    write_scene_predictions(submission, scene_set, noisy_constant_velocity(scene_set.windows, 3),
                            grid)
    written = scene_rows(submission)
    assert [row["id"] for row in written] == expected and len(expected) > 150
    by_id = {row["id"]: row for row in scene_rows(source)}
    assert all(row == by_id[row["id"]] for row in written)       # primary, frames, fps, tag

    truth = with_scenes(source, expected, tmp_path / "truth.ndjson")
    official = official_figures(truth, submission)
    # `evaluate --predictions` steps once a row of the file: WILDTRACK's 2 Hz, 0.5 s.
    ours = evaluate_prediction_file(submission, config, "test", with_kde=False)
    assert_same_figures(ours["trajnet"], official, samples=3)
    assert official["col_ii_percent"] > 0                     # not a vacuous match
    # TrajNet++'s top-k FDE is the best-ADE sample's: not the least FDE, gst_jax's minFDE.
    figures = ours["trajnet"]
    assert figures["topk_ade"] == figures["top3_ade"] and figures["topk_fde"] == figures["top3_fde"]
    assert ours["pedestrians"] > len(expected) and "aoe" in ours     # per pedestrian, beside
    # Constant velocity on the same primaries: the truth's rows 7 and 8, the last two observed.
    cv_ade, cv_fde = [], []
    for _, paths in trajnet.Reader(str(truth), scene_type="paths").scenes():
        (x7, y7), (x8, y8) = [(row.x, row.y) for row in paths[0][OBS_LENGTH - 2:OBS_LENGTH]]
        future = [trajnet.TrackRow(row.frame, row.pedestrian, x8 + t * (x8 - x7),
                                   y8 + t * (y8 - y7))
                  for t, row in enumerate(paths[0][OBS_LENGTH:], 1)]
        cv_ade.append(trajnet.metrics.average_l2(paths[0], future, n_predictions=PRED_LENGTH))
        cv_fde.append(trajnet.metrics.final_l2(paths[0], future))
    assert figures["cv_ade"] == pytest.approx(np.mean(cv_ade), abs=1e-6)
    assert figures["cv_fde"] == pytest.approx(np.mean(cv_fde), abs=1e-6)

    # A file whose scenes come in another order, or whose primary lacks a scored frame, is
    # refused as the evaluator would refuse it.
    lines = submission.read_text().splitlines()
    heads = [i for i, line in enumerate(lines) if '"scene"' in line]
    swapped = lines[heads[1]:heads[2]] + lines[:heads[1]] + lines[heads[2]:]
    (tmp_path / "swapped.ndjson").write_text("\n".join(swapped) + "\n")
    with pytest.raises(DataError, match=r"swapped.ndjson:1: scene row 1 is scene .* pairs the "
                                        "two files' scenes in order"):
        evaluate_prediction_file(tmp_path / "swapped.ndjson", config, "test")
    (tmp_path / "short.ndjson").write_text("\n".join(lines[:heads[0] + 1]
                                                     + lines[heads[0] + 2:]) + "\n")
    with pytest.raises(DataError, match="has no prediction 0 at frame .*\"frame numbers are not "
                                        "consistent"):
        evaluate_prediction_file(tmp_path / "short.ndjson", config, "test")


def test_scenes_the_model_cannot_read_row_for_row_are_refused_with_the_fix(tmp_path):
    # WILDTRACK as --scene reads it, at its own 2 Hz: 0.5 s rows, the model's steps 0.4 s.
    with pytest.raises(DataError, match=r"wildtrack.ndjson: its rows are 0.5 s apart .* a model "
                                        r"with --step 0.5, or --data .* --fps 12.5"):
        load_scenes(DataConfig(scene="wildtrack"), "test", GRID)
    first_scene = with_scenes(TRAJNET / "lcas.ndjson", [0], tmp_path / "one.ndjson")
    with pytest.raises(DataError, match=r"one.ndjson: none of its scenes lies within the frames "
                                        r"of the test split's windows .* --split all"):
        load_scenes(DataConfig(scene="one", data=str(first_scene)), "test", GRID)
    assert [scene.scene_id for scene in load_scenes(
        DataConfig(scene="one", data=str(first_scene)), "all", GRID).scenes] == [0]


def _fully_neighboured(source: Path, step: int) -> list[int]:
    """Scenes whose TrajNet++ neighbours (a row before the first predicted one) are all seen
    at the last two observed rows, so that a model predicts every one (docs/MODEL.md 2.3):
    Col-I is defined."""
    rows = [json.loads(line)["track"] for line in source.read_text().splitlines()
            if '"track"' in line]
    seen: dict[int, set] = {}
    for row in rows:
        seen.setdefault(row["f"], set()).add(row["p"])
    chosen = []
    for scene in scene_rows(source):
        before = set().union(*(seen.get(scene["s"] + r * step, set()) for r in range(OBS_LENGTH)))
        last_two = (seen.get(scene["s"] + (OBS_LENGTH - 2) * step, set())
                    & seen.get(scene["s"] + (OBS_LENGTH - 1) * step, set()))
        if before and before <= last_two:
            chosen.append(scene["id"])
    return chosen


def test_col_i_and_nll_where_trajnet_defines_them(tmp_path):
    source = TRAJNET / "wildtrack.ndjson"
    chosen = _fully_neighboured(source, step=5)[:10]
    truth = with_scenes(source, chosen, tmp_path / "truth.ndjson")
    config = dataclasses.replace(WILDTRACK, data=str(truth))
    scene_set = load_scenes(config, "all", GRID)
    submission = tmp_path / "submission.ndjson"
    write_scene_predictions(submission, scene_set,
                            noisy_constant_velocity(scene_set.windows, 50, seed=3, step_m=0.5),
                            GRID)
    official = official_figures(truth, submission)
    ours = evaluate_prediction_file(submission, config, "all", with_kde=False)["trajnet"]
    assert official["col_i_percent"] != -1 and ours["col_i_undefined_scenes"] == 0
    assert_same_figures(ours, official, samples=50)
    assert official["col_i_percent"] > 0 and official["log_likelihood"] != 0


@pytest.fixture(scope="module")
def tiny_model() -> Run:
    """A GST (P) of one small layer, untrained: its samples differ."""
    config = ModelConfig(node_dim=8, edge_dim=16, encoder_layers=1, encoder_ff_dim=16,
                         lstm_hidden=8, output="gaussian")
    return Run(name="tiny", model_config=config, data_config=LCAS, train_config=TrainConfig(),
               params=init_params(config, jax.random.key(0)), epoch=0, workdir=None)


def test_a_model_writes_a_submission_that_evaluate_scores_as_trajnet_does(tiny_model,
                                                                            tmp_path, capsys):
    source = TRAJNET / "lcas.ndjson"
    # Four scenes of at most 10 people in the model's rows: one or two batch shapes to compile.
    rows = [json.loads(line)["track"] for line in source.read_text().splitlines()
            if '"track"' in line]
    small = [scene["id"] for scene in scene_rows(source)
             if len({row["p"] for row in rows if scene["s"] < row["f"] <= scene["e"]}) <= 10]
    assert len(small) >= 4
    truth = with_scenes(source, small[:4], tmp_path / "truth.ndjson")
    config = DataConfig(scene="truth", data=str(truth))
    written = write_run_predictions(tiny_model, config, "all", tmp_path / "submission.ndjson",
                                    num_samples=3, seed=1)
    assert written.answers == "4 TrajNet++ scenes of truth.ndjson"
    official = official_figures(truth, tmp_path / "submission.ndjson")
    evaluate_main(["--predictions", str(tmp_path / "submission.ndjson"), "--data", str(truth),
                   "--split", "all", "--json"])
    printed = json.loads(capsys.readouterr().out)
    assert_same_figures(printed["trajnet"], official, samples=3)
    assert printed["trajnet"]["ade"] > 0 and printed["pedestrians"] >= 4
