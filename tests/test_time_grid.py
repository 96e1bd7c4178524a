"""A model on another time grid: CrowdNav++'s 0.25 s, 5 observed and 5 predicted steps, with
its architecture, through the same commands as the paper's model, on the navigation task's
own humans."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gst_jax import evaluate, plot, train
from gst_jax.config import DataConfig, TimeGrid
from gst_jax.data import load_split
from gst_jax.predict.__main__ import main as predict_main
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.crowds import Condition, write_crowds
from gst_jax.testing.drawn import line_data, saved_figures

CROWDNAV = ["--fps", "4", "--step", "0.25", "--obs-len", "5", "--pred-len", "5",
            "--edge-heads", "0", "--no-ghost", "--node-dim", "16", "--encoder-layers", "1",
            "--lstm-dim", "16", "--temporal", "faster_lstm", "--output", "gaussian"]


@pytest.fixture(scope="module")
def crowds(tmp_path_factory) -> Path:
    """Two short episodes of the navigation task's own humans (8 ORCA humans, 12 s at 0.25 s),
    written as `python -m gst_jax.navigate crowds` writes its files."""
    folder = tmp_path_factory.mktemp("crowds")
    write_crowds(folder, (Condition(num_humans=8),), episodes=2, seed=0, steps=48)
    return folder


def test_a_0_25s_model_trains_evaluates_predicts_and_plots_through_the_commands(
        crowds, tmp_path, capsys):
    run = tmp_path / "run"
    train.main(["--data", str(crowds), *CROWDNAV, "--epochs", "1", "--batch-size", "8",
                "--max-train-windows", "16", "--workdir", str(run)])
    config = json.loads((run / "config.json").read_text())
    assert (config["model"]["step_s"], config["model"]["obs_len"]) == (0.25, 5)
    capsys.readouterr()
    evaluate.main([str(run), "--samples", "3", "--json"])
    result = json.loads(capsys.readouterr().out)
    assert result["pedestrians"] > 0 and np.isfinite(result["aoe"])
    assert "cv_aoe" in result

    out = tmp_path / "predictions.ndjson"
    predict_main([str(run), "--samples", "2", "--out", str(out)])
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert {row["scene"]["fps"] for row in rows if "scene" in row} == {4.0}
    # Each window's 5 observed and 5 predicted steps are one frame (0.25 s at 4 fps) apart.
    scene = next(row["scene"] for row in rows if "scene" in row)
    assert scene["e"] - scene["s"] == 9

    # The scene figure draws the window on the model's grid: 5 observed steps, 5 predicted.
    with saved_figures() as saved:
        plot.main(["scene", str(run), "--samples", "2", "--out", str(tmp_path / "scene.png")])
    trained = load_model(str(run))
    window = load_split(trained.data_config, "test", trained.model_config.grid)[0]
    seen = window.position_mask[:5] > 0
    paths = saved[tmp_path / "scene.png"].axes[0]
    observed = line_data(paths, "tab:blue")
    assert len(observed) == seen.any(axis=0).sum()
    for xy, person in zip(observed, np.flatnonzero(seen.any(axis=0))):
        np.testing.assert_array_equal(xy, window.positions[:5][seen[:, person], person])
    samples = line_data(paths, "tab:red") + line_data(paths, "tab:orange")
    assert len(samples) == 3 * seen[-1].sum()         # 2 samples and their mean per person
    assert all(xy.shape == (5, 2) and np.isfinite(xy).all() for xy in samples)


def test_its_windows_follow_the_model_s_grid_and_bundled_scenes_refuse_it(crowds, capsys):
    grid = TimeGrid(step_s=0.25, obs_len=5, pred_len=5)
    windows = load_split(DataConfig(scene="sim", data=str(crowds), fps=4), "train", grid)
    assert windows[0].positions.shape[0] == 10
    with pytest.raises(SystemExit, match="annotated at 2.5 Hz .* not a multiple of the "
                                         "model's 4 Hz"):
        train.main(["--scene", "zara1", *CROWDNAV[2:], "--epochs", "1"])
