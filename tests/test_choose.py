"""`python -m gst_jax.pretrained choose`: the shipped models whose time step fits your data, and
constant velocity, ranked on its validation windows (gst_jax/pretrained/choose.py)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from gst_jax import data
from gst_jax.config import DataConfig, TimeGrid
from gst_jax.errors import DataError
from gst_jax.evaluation import evaluate_run
from gst_jax.pretrained import choose
from gst_jax.pretrained.__main__ import main
from gst_jax.runs import load_model

SAMPLE = Path(__file__).parents[1] / "data" / "samples" / "crowd_10hz.txt"
OWN = DataConfig(scene="crowd_10hz", protocol="paper-val", data=str(SAMPLE), fps=10, scale=0.01)
# Two models of one architecture (one compile between them), and one on CrowdNav++'s 0.25 s
# grid, which 10 Hz frame ids cannot give (its steps fall between them).
MODELS = ("hotel_d", "zara1_d", "crowdnav_sim")
SAMPLES = 2


@pytest.fixture(scope="module")
def chosen() -> choose.Choice:
    return choose.choose(OWN, MODELS, num_samples=SAMPLES)


def test_the_ranking_follows_evaluates_scores_on_the_validation_windows(chosen):
    """Each row is `evaluate`'s AOE / FOE on the same split with the same samples, constant
    velocity's its cv_aoe, and the rows are ranked by them."""
    expected = {}
    for name in MODELS[:2]:
        result = evaluate_run(load_model(f"pretrained:{name}"), OWN, "val",
                              num_samples=SAMPLES, with_kde=False)
        expected[f"pretrained:{name}"] = (result["aoe"], result["foe"])
        expected[choose.CONSTANT_VELOCITY] = (result["cv_aoe"], result["cv_foe"])
    (table,) = chosen.tables
    assert table.grid == TimeGrid() and table.windows == len(data.load_split(OWN, "val"))
    assert [row.name for row in table.rows] == sorted(expected, key=lambda n: expected[n][0])
    for row in table.rows:
        assert (row.aoe, row.foe) == pytest.approx(expected[row.name], rel=1e-6), row.name
        assert row.aoe_interval[0] <= row.aoe <= row.aoe_interval[1]
        cv_aoe = expected[choose.CONSTANT_VELOCITY][0]
        assert row.minus_cv == pytest.approx(row.aoe - cv_aoe, abs=1e-9)


def test_a_model_whose_time_step_does_not_fit_is_skipped_with_the_data_layers_reason(chosen):
    grid = choose.model_grid("crowdnav_sim")
    with pytest.raises(DataError) as refusal:
        data.load_split(OWN, "val", grid)
    (skipped,) = chosen.skipped
    assert skipped == ("crowdnav_sim", f"time step 0.25 s, 5 observed + 5 predicted steps: "
                                       f"{refusal.value}")
    printed = choose.format_choice(chosen)
    assert f"skipped crowdnav_sim: {skipped[1]}" in printed


def test_intervals_are_a_bootstrap_over_windows_paired_with_constant_velocity():
    """Two windows of one pedestrian each: a model 0.5 m off in both, constant velocity 0 and
    2 m off. Resampling the windows gives constant velocity 0, 1 or 2 m (the 2.5 and 97.5 %
    quantiles: 0 and 2), the model always 0.5, their difference 0.5 - CV."""
    sums = {"pretrained:a": (np.array([0.5, 0.5]), np.array([1.0, 1.0])),
            choose.CONSTANT_VELOCITY: (np.array([0.0, 2.0]), np.array([0.0, 4.0]))}
    table = choose.ranked_table(TimeGrid(), sums, np.array([1, 1]))
    model, cv = table.rows
    assert (model.name, model.aoe, model.foe, model.aoe_interval) == (
        "pretrained:a", 0.5, 1.0, (0.5, 0.5))
    assert (cv.aoe, cv.foe, cv.aoe_interval) == (1.0, 2.0, (0.0, 2.0))
    assert (model.minus_cv, model.minus_cv_interval) == (-0.5, (-1.5, 0.5))
    assert (table.windows, table.pedestrians, table.best_model) == (2, 2, model)


@pytest.mark.parametrize("model_ade, advice", [
    ((0.5, 0.5), "Start from pretrained:a (AOE - CV -1.000 m, 95 % -1.500 to -0.500)"),
    ((0.2, 2.6), "pretrained:a leads constant velocity on these windows, but not beyond the "
                 "95 % interval (AOE - CV -0.100 m, 95 % -0.800 to +0.600)"),
    ((2.0, 2.0), "Constant velocity beats every shipped model on these windows")])
def test_the_advice_follows_the_paired_interval_and_notes_a_bundled_scenes_training(model_ade,
                                                                                    advice):
    """Constant velocity 1 and 2 m off on two windows; a model ahead of it on both (its
    interval below zero), ahead on the mean only (0.2 and 2.6: the resamples of the second
    window alone put it behind), or behind. On a bundled scene the windows lie in the split its
    models trained on, and the command fine-tunes with --scene."""
    sums = {"pretrained:a": (np.array(model_ade), np.array(model_ade)),
            choose.CONSTANT_VELOCITY: (np.array([1.0, 2.0]), np.array([1.0, 2.0]))}
    table = choose.ranked_table(TimeGrid(), sums, np.array([1, 1]))
    bundled = DataConfig(scene="zara1", protocol="paper-val")
    printed = choose.format_choice(choose.Choice(bundled, 20, (table,), ()))
    assert advice in printed
    assert "note: zara1's validation windows lie in its paper train split" in printed
    assert printed.splitlines()[-1].split()[3:7] == ["--scene", "zara1", "--init",
                                                       "pretrained:a"]
    own = choose.format_choice(choose.Choice(OWN, 20, (table,), ()))
    assert "note:" not in own


def test_the_command_prints_the_table_and_a_fine_tuning_command_train_accepts(capsys):
    main(["choose", "--data", str(SAMPLE), "--fps", "10", "--units", "cm", "--models",
          "hotel_d, crowdnav_sim", "--samples", str(SAMPLES)])
    printed = capsys.readouterr()
    lines = printed.out.splitlines()
    ranked = [re.match(r"(\d+) +(constant velocity|pretrained:\S+) +([\d.]+) ", line)
              for line in lines]
    ranks, names, aoes = zip(*(match.groups() for match in ranked if match))
    assert ranks == ("1", "2") and set(names) == {"pretrained:hotel_d", "constant velocity"}
    assert float(aoes[0]) <= float(aoes[1])
    assert "models scored 1/1 (hotel_d)" in printed.err
    command = shlex.split(lines[-1])
    assert command[:3] == ["python3", "-m", "gst_jax.train"]
    flags = dict(zip(command[3::2], command[4::2]))
    assert {k: flags[k] for k in ("--fps", "--units", "--init")} == {
        "--fps": "10", "--units": "cm", "--init": "pretrained:hotel_d"}
    assert Path(flags["--data"]).resolve() == SAMPLE.resolve()


def test_data_no_model_reads_is_refused_in_one_line(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["choose", "--data", str(SAMPLE), "--fps", "10", "--units", "cm", "--models",
              "crowdnav_sim"])
    assert str(stop.value).startswith(f"error: {SAMPLE}: annotated at 10 Hz")
    with pytest.raises(SystemExit):                      # neither --data nor --scene
        main(["choose"])
    assert "one of the arguments --scene --data is required" in capsys.readouterr().err
