"""Your own data: any rate the model's steps fit, any unit, every model, fine-tuning."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
import warnings
from pathlib import Path

import chex
import numpy as np
import pytest

from gst_jax import data
from gst_jax.config import DataConfig, ModelConfig, TimeGrid, TrainConfig
from gst_jax.errors import DataError, RunError
from gst_jax.evaluation import evaluate_run
from gst_jax.io.workdir import WorkDir
from gst_jax.runs import load_model, load_run
from gst_jax.testing.drawn import pixels_near
from gst_jax.train import format_fine_tuning
from gst_jax.training.loop import fit
from gst_jax.training.state import TrainState, hparams_for_epoch, step_key
from gst_jax.training.step import make_train_step

SAMPLE = Path(__file__).parents[1] / "data" / "samples" / "crowd_10hz.txt"
TINY = TrainConfig(epochs=1, batch_size=8, max_train_windows=8, checkpoint_every=1)


@pytest.fixture(scope="module")
def at_model_rate(tmp_path_factory) -> Path:
    """The sample pre-resampled by hand: every 4th row of 10 Hz, frame ids 0, 10, 20, ... as
    ETH/UCY number them, metres."""
    rows = np.loadtxt(SAMPLE)
    rows = rows[rows[:, 0] % 4 == 0]
    path = tmp_path_factory.mktemp("own") / "crowd_2_5hz.txt"
    path.write_text("".join(f"{int(f) * 10 // 4} {int(p)} {float(x) / 100!r} {float(y) / 100!r}\n"
                            for f, p, x, y in rows))
    return path


def _configs(at_model_rate: Path) -> tuple[DataConfig, DataConfig]:
    return (DataConfig(scene="crowd_10hz", data=str(SAMPLE), fps=10, scale=0.01),
            DataConfig(scene="crowd_2_5hz", data=str(at_model_rate)))


def test_a_10hz_file_in_centimetres_gives_the_windows_of_the_same_data_at_2_5hz(at_model_rate):
    ours, by_hand = _configs(at_model_rate)
    for split in ("train", "test", "all"):
        a, b = data.load_split(ours, split), data.load_split(by_hand, split)
        assert len(a) == len(b) > 0, split
        for x, y in zip(a.windows, b.windows):
            np.testing.assert_allclose(x.positions, y.positions, rtol=0, atol=1e-5)
            np.testing.assert_array_equal(x.position_mask, y.position_mask)


def test_train_and_evaluate_on_it_equal_the_pre_resampled_data(tmp_path, at_model_rate):
    results = []
    for config, name in zip(_configs(at_model_rate), ("a", "b")):
        # One encoder layer compiles faster; the equality does not depend on the depth.
        summary = fit(ModelConfig(encoder_layers=1), config, TINY, tmp_path / name)
        run = load_run(tmp_path / name)
        results.append((summary["final_loss"], evaluate_run(run, config, "test", num_samples=2,
                                                            with_kde=False)))
    (loss_a, eval_a), (loss_b, eval_b) = results
    assert loss_a == pytest.approx(loss_b, rel=1e-5)
    for name in ("aoe", "foe", "min_ade", "cv_aoe"):
        assert eval_a[name] == pytest.approx(eval_b[name], rel=1e-4), name
    assert eval_a["scene"] == "crowd_10hz" and eval_a["windows"] == eval_b["windows"]


def _command(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          timeout=600, cwd=cwd)


def test_a_rate_whose_steps_fall_between_frame_ids_is_refused(tmp_path):
    result = _command("gst_jax.train", "--data", str(SAMPLE), "--fps", "3",
                      "--workdir", str(tmp_path / "run"))
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines()[-1] == (
        f"error: {SAMPLE}: annotated at 3 Hz (a row every frame id at 3 per second), not a "
        "multiple of the model's 2.5 Hz, and its 0.4 s steps would fall between frame ids (1.2 "
        "apart); number its frames in finer units (frame ids x5, read with --fps 15)")
    assert not (tmp_path / "run").exists()


def test_a_shipped_model_evaluates_and_plots_own_data_from_any_folder(tmp_path):
    relative = SAMPLE.relative_to(SAMPLE.parents[3])        # from the repository's parent
    result = _command("gst_jax.evaluate", "pretrained:hotel_d", "--data", str(relative),
                      "--fps", "10", "--units", "cm", "--samples", "2", "--no-kde", "--json",
                      cwd=SAMPLE.parents[3])
    assert result.returncode == 0, result.stderr
    evaluation = json.loads(result.stdout)
    assert evaluation["model"] == "pretrained:hotel_d" and evaluation["scene"] == "crowd_10hz"
    assert 0 < evaluation["aoe"] < evaluation["foe"] < 5
    figure = tmp_path / "scene.png"
    result = _command("gst_jax.plot", "scene", "pretrained:hotel_d", "--data", str(SAMPLE),
                      "--fps", "10", "--units", "cm", "--samples", "2", "--out", str(figure),
                      cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    # Drawn: observed (blue) and true (green) paths and predictions (red where fully
    # detected, orange where not), each far beyond its legend's 96 pixels.
    drawn = {colour: pixels_near(figure, colour)
             for colour in ("tab:blue", "tab:green", "tab:red", "tab:orange")}
    assert drawn["tab:blue"] > 500 and drawn["tab:green"] > 500, drawn
    assert drawn["tab:red"] + drawn["tab:orange"] > 500, drawn


def test_fine_tuning_starts_from_the_given_parameters(tmp_path, at_model_rate):
    config = _configs(at_model_rate)[1]
    source = load_model("pretrained:hotel_d")
    train_config = dataclasses.replace(TINY, init="pretrained:hotel_d")
    summary = fit(source.model_config, config, train_config, tmp_path / "tuned")
    # One step: the epoch's loss is the loss of the shipped parameters on that step.
    step = next(iter(data.training_batches(data.load_split(config, "train").subset(range(8)),
                                           batch_size=8, seed=train_config.seed, epoch=1)))
    hparams = hparams_for_epoch(source.model_config, train_config, 1)
    train_step = make_train_step(source.model_config)    # fit's, with its compiled programs
    # Placed as fit places them: unplaced (uncommitted) arrays would compile the step again.
    loss, _ = train_step.loss_and_grads(*map(train_step.place, (
        source.params, step_key(train_config.seed, 1, 0))), step, train_step.place(hparams))
    assert summary["final_loss"] == pytest.approx(float(loss), rel=1e-5)
    with pytest.raises(RunError, match="another architecture"):
        fit(ModelConfig(temporal="tcn"), config, train_config, tmp_path / "tcn")
    assert not (tmp_path / "tcn").exists()
    assert WorkDir(tmp_path / "tuned").read_metrics()[0]["epoch"] == 1


def test_fine_tuning_selects_its_epoch_on_validation_and_reports_beside_the_start(tmp_path):
    """`train --init`: a validation split carved from the training data, a constant small
    learning rate at the model's end temperature, the epoch (0 = the start) of the best
    validation AOE kept in selected/ and read by every command, and the kept model, the
    starting one and constant velocity scored on the same test windows."""
    workdir = tmp_path / "tuned"
    trained = subprocess.run(
        [sys.executable, "-m", "gst_jax.train", "--data", str(SAMPLE), "--fps", "10", "--units",
         "cm", "--init", "pretrained:hotel_d", "--epochs", "1", "--workdir", str(workdir),
         "--json"], capture_output=True, text=True, timeout=900)
    assert trained.returncode == 0, trained.stderr
    summary = json.loads(trained.stdout)
    config = summary["config"]
    assert config["data"]["protocol"] == "paper-val"
    assert (config["train"]["schedule"], config["train"]["learning_rate"]) == ("finetune", 1e-4)
    records = WorkDir(workdir).read_metrics()
    assert [r["tau"] for r in records] == pytest.approx([0.03])
    report = summary["fine_tuning"]
    kept = report["selected_epoch"]
    assert kept == records[-1]["selected_epoch"] == 0
    assert all(r["val_aoe"] >= report["val_aoe"] for r in records)
    # What docs/own-data.md's recipe (10 epochs, an excerpt) prints: no epoch improves on
    # this sample, so the first does not either.
    assert format_fine_tuning(report).splitlines()[0] == (
        "kept the starting model (pretrained:hotel_d): no epoch improved on validation AOE "
        "(0.226 m, 3 windows)")
    run, source = load_model(str(workdir)), load_model("pretrained:hotel_d")
    assert run.epoch == kept
    # The kept model is the start, parameter for parameter, so one evaluation scores both.
    chex.assert_trees_all_equal(run.params, source.params)
    data_config = DataConfig.from_dict(config["data"])
    start = evaluate_run(source, data_config, "test", with_kde=False)
    test = report["test"]
    assert test["windows"] == start["windows"] == 8
    assert test["start"] == test["tuned"] == {"aoe": start["aoe"], "foe": start["foe"]}
    assert test["constant_velocity"] == {"aoe": start["cv_aoe"], "foe": start["cv_foe"]}


def test_a_fine_tuning_reports_the_starting_models_validation_aoe_beside_the_kept_ones(
        tmp_path, monkeypatch):
    """What docs/own-data.md tells the user to compare: the kept epoch's validation AOE and
    the starting model's, kept with the selection across epochs (scores stand in for the
    evaluations: nothing compiles)."""
    from gst_jax.training.selection import Selection

    data_config = DataConfig(scene="crowd_10hz", data=str(SAMPLE), fps=10, scale=0.01,
                             protocol="paper-val")
    train_config = dataclasses.replace(TINY, init="pretrained:hotel_d")
    selection = Selection(ModelConfig(), data_config, train_config, WorkDir(tmp_path),
                          {"run": "stand-in"}, None)
    val_aoe = {"start": 0.162, "epoch 1": 0.170, "epoch 2": 0.149, "epoch 3": 0.155}
    scoring = iter(val_aoe.values())
    monkeypatch.setattr(selection, "_score", lambda params, window_set, key: {
        "aoe": next(scoring, 0.3), "foe": 0.5, "cv_aoe": 0.2, "cv_foe": 0.4})
    def state(epoch: int) -> TrainState:
        return TrainState(params={"w": np.full(2, epoch, np.float32)}, opt_state={},
                          step=np.int32(epoch))

    selection.start(lambda: state(0))
    for epoch in (1, 2, 3):
        selection.after_epoch(epoch, state(epoch))
    source = dataclasses.replace(load_model("pretrained:hotel_d"), params=state(0).params)
    report = selection.report(source, state(3), data_config)
    assert (report["selected_epoch"], report["val_aoe"]) == (2, 0.149)
    assert report["start_val_aoe"] == 0.162
    assert format_fine_tuning(report).splitlines()[0] == (
        "kept epoch 2 on validation AOE (0.149 m against 0.162 m for the starting model "
        f"pretrained:hotel_d, {report['val_windows']} windows)")


# --- trackers' CSV files: a header, --columns ----------------------------------------------

MOT_SAMPLE = SAMPLE.with_name("crowd_mot.csv")


def _same_windows(a: data.WindowSet, b: data.WindowSet) -> None:
    assert len(a) == len(b) > 0
    for x, y in zip(a.windows, b.windows):
        np.testing.assert_allclose(x.positions, y.positions, rtol=0, atol=1e-5)
        np.testing.assert_array_equal(x.position_mask, y.position_mask)


@pytest.mark.parametrize("columns", [None, "1,2,8,9", "frame,id,x,y", "FRAME, ID, 8, y"])
def test_a_motchallenge_csv_reads_as_the_same_data_in_frame_ped_x_y(columns):
    """crowd_mot.csv is crowd_10hz.txt at 2.5 Hz in metres, as MOTChallenge rows under a
    header: its frame, id, x, y are found by name, or by --columns (names or numbers)."""
    mot = DataConfig(scene="crowd_mot", data=str(MOT_SAMPLE), fps=10, columns=columns)
    _same_windows(data.load_split(mot, "all"), data.load_split(_configs(SAMPLE)[0], "all"))


@pytest.mark.parametrize("header, separator", [
    ("frame,id,x,y", ","), ("frame ped x y", " "), ("Frame,Track_ID,conf,X,Y", ","),
    ("frame_id\tpedestrian_id\tx\ty", "\t"), (None, ","),
])
def test_headers_with_the_usual_names_and_csv_without_one_need_no_flag(tmp_path, header,
                                                                        separator):
    rows = [(f, p, 0.5 * f / 10 + p, 0.25 * p) for f in range(0, 300, 10) for p in (1, 2, 3)]
    bare = tmp_path / "bare.txt"
    bare.write_text("".join(f"{f} {p} {x} {y}\n" for f, p, x, y in rows))
    conf = header is not None and "conf" in header
    lines = [separator.join(map(str, (f, p, *((0.9,) if conf else ()), x, y)))
             for f, p, x, y in rows]
    path = tmp_path / "tracker.csv"
    path.write_text("\n".join(([header] if header else []) + lines) + "\n")
    ours, expected = data.read_tracks(path), data.read_tracks(bare)
    for name in ("frames", "pedestrians", "xy"):
        np.testing.assert_array_equal(getattr(ours, name), getattr(expected, name))


def test_folders_and_globs_of_own_data_include_csv_files(tmp_path):
    (tmp_path / "a.csv").write_text(MOT_SAMPLE.read_text())
    assert data.data_files(str(tmp_path)) == [tmp_path / "a.csv"]


def _parsed(*argv: str, base: DataConfig | None = None) -> DataConfig:
    import argparse

    from gst_jax import cli

    parser = argparse.ArgumentParser()
    cli.add_data_flags(parser, of_run=base is not None)
    return cli.data_config(parser.parse_args(argv), base)


def test_columns_are_stored_in_the_run_and_read_the_same_way_again():
    config = _parsed("--data", str(MOT_SAMPLE), "--fps", "10", "--columns", "1, 2,8,9")
    assert config.columns == "1,2,8,9"
    assert DataConfig.from_dict(json.loads(json.dumps(dataclasses.asdict(config)))) == config
    assert _parsed("--protocol", "paper", base=config) == config     # a trained run's own
    with pytest.raises(SystemExit):                    # argparse: exit 2 with one line
        _parsed("--data", str(MOT_SAMPLE), "--columns", "1,2,8")


def test_a_run_config_written_before_columns_existed_is_the_same_run():
    from gst_jax.io.workdir import run_config, same_run

    new = run_config(ModelConfig(), DataConfig(scene="own", data="/x/own.txt"), TrainConfig())
    old = json.loads(json.dumps(new))
    del old["data"]["columns"]
    assert DataConfig.from_dict(old["data"]) == DataConfig(scene="own", data="/x/own.txt")
    assert same_run(old, new) and same_run(new, old)


@pytest.mark.parametrize("command", [
    ["gst_jax.train"], ["gst_jax.evaluate"], ["gst_jax.predict"], ["gst_jax.plot", "scene"],
    ["gst_jax.sweep"], ["gst_jax.data", "stats"],
])
def test_every_command_that_takes_data_takes_columns(capsys, command):
    import importlib

    name = command[0] if command[0] in ("gst_jax.train", "gst_jax.evaluate", "gst_jax.plot",
                                        "gst_jax.sweep") else command[0] + ".__main__"
    with pytest.raises(SystemExit) as exit_:
        importlib.import_module(name).main([*command[1:], "--help"])
    help_text = capsys.readouterr().out
    assert exit_.value.code == 0
    assert "--data PATH" in help_text and "--columns F,ID,X,Y" in help_text


def test_the_stats_command_reads_a_mot_file_by_column_numbers():
    def stats(*args: str) -> dict:
        result = _command("gst_jax.data", "stats", "--json", *args)
        assert result.returncode == 0, result.stderr
        return next(iter(json.loads(result.stdout)["scenes"].values()))

    assert (stats("--data", str(MOT_SAMPLE), "--fps", "10", "--columns", "1,2,8,9")
            == stats("--data", str(SAMPLE), "--fps", "10", "--units", "cm"))


# --- walking speeds: a wrong --units or --fps -----------------------------------------------

def _scaled_sample(path: Path, factor: float) -> Path:
    rows = np.loadtxt(SAMPLE)
    path.write_text("".join(f"{int(f)} {int(p)} {float(x) * factor!r} {float(y) * factor!r}\n"
                            for f, p, x, y in rows))
    return path


def test_coordinates_a_billion_times_too_large_are_refused_in_one_line(tmp_path):
    path = _scaled_sample(tmp_path / "huge.txt", 1e9 / 100)        # metres x 1e9
    result = _command("gst_jax.data", "stats", "--data", str(path), "--fps", "10")
    assert result.returncode == 1 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [
        f"error: {path}: its people move at a median 1.13e+09 m/s (read in m, frame ids at 10 "
        "per second), which no pedestrian does; no --units makes that a walking speed: check "
        "the coordinates, and --fps (frame ids per second: a wrong rate scales every speed)"]


def test_centimetres_read_as_metres_are_refused_with_the_units_that_fix_them():
    config = DataConfig(scene="crowd_10hz", data=str(SAMPLE), fps=10)           # no --units cm
    with pytest.raises(DataError, match=rf"^{SAMPLE}: its people move at a median 113 m/s "
                                        r"\(read in m, frame ids at 10 per second\), which no "
                                        r"pedestrian does; in cm it would be 1\.1 m/s: add "
                                        r"--units cm$"):
        data.load_split(config, "train")


def test_metres_read_as_centimetres_are_warned_about(tmp_path):
    path = _scaled_sample(tmp_path / "metres.txt", 1 / 100)
    config = DataConfig(scene="metres", data=str(path), fps=10, scale=0.01)
    with pytest.warns(UserWarning, match=r"90% of its steps are slower than 0\.0142 m/s "
                                         r"\(median 0\.0113 m/s, read in cm, frame ids at 10 per "
                                         r"second\), slow for pedestrians; in m it would be "
                                         r"1\.1 m/s: use --units m"):
        assert len(data.load_split(config, "train")) == 33


def _renumbered_at_2_5hz(path: Path) -> Path:
    """The sample at 2.5 Hz in metres, its frame ids counting every row: 0, 1, 2, ..."""
    rows = np.loadtxt(SAMPLE)
    rows = rows[rows[:, 0] % 4 == 0]
    path.write_text("".join(f"{int(f) // 4} {int(p)} {float(x) / 100!r} {float(y) / 100!r}\n"
                            for f, p, x, y in rows))
    return path


def test_a_wrong_fps_is_named_before_a_unit_when_a_frame_rate_explains_the_speeds(tmp_path):
    """2.5 Hz data read with --fps 25 walk 10x too fast: ft (3.3x) would bring them under the
    refusal, but --fps 2.5 brings them to a crowd's speed."""
    path = _renumbered_at_2_5hz(tmp_path / "at_2_5hz.txt")
    with pytest.raises(DataError, match=rf"^{path}: its people move at a median 10\.5 m/s "
                                        r"\(read in m, frame ids at 25 per second\), which no "
                                        r"pedestrian does; at --fps 2\.5 it would be 1 m/s: "
                                        r"check --fps \(frame ids per second: a wrong rate "
                                        r"scales every speed\); in ft it would be 3\.2 m/s "
                                        r"\(--units ft\)$"):
        data.load_split(DataConfig(scene="at_2_5hz", data=str(path), fps=25), "train")


def test_a_trackers_frame_ids_read_without_fps_are_warned_about(tmp_path, at_model_rate):
    """The 10 Hz sample without --fps is read as 2.5 Hz: its people walk a quarter of their
    speed, slowly enough to pass the speed check. Data whose ids count 2.5 per second (every
    row, or every 10th id as ETH/UCY) read silently."""
    with pytest.warns(UserWarning, match=rf"^{SAMPLE}: no --fps, so its rows are taken to be "
                                         r"the model's steps, 0\.4 s apart, where its people "
                                         r"walk a median 0\.28 m/s; its frame ids count every "
                                         r"frame, as a video's or a tracker's do: at --fps 10 "
                                         r"they would walk 1\.1 m/s \(give --fps, the frame ids "
                                         r"per second\)$"):
        data.load_split(DataConfig(scene="no_fps", data=str(SAMPLE), scale=0.01), "train")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for path in (_renumbered_at_2_5hz(tmp_path / "every_row.txt"), at_model_rate):
            assert len(data.load_split(DataConfig(scene=path.stem, data=str(path)), "all"))


def test_the_bundled_scenes_and_samples_pass_the_speed_check_silently():
    from gst_jax.config import CROWD_SCENES
    from gst_jax.data import protocols

    protocols._tracks.cache_clear()          # a check warns once per file: start afresh
    protocols._cut.cache_clear()
    configs = [(DataConfig(scene=scene), TimeGrid()) for scene in CROWD_SCENES]
    configs += [(_configs(SAMPLE)[0], TimeGrid()),
                (DataConfig(scene="crowd_mot", data=str(MOT_SAMPLE), fps=10), TimeGrid()),
                (DataConfig(scene="sim", data=str(SAMPLE.parent / "crowdnav_orca"), fps=4),
                 TimeGrid(step_s=0.25, obs_len=5, pred_len=5))]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for config, grid in configs:
            assert len(data.load_split(config, "all", grid)) > 0, config.scene


# --- files without windows -----------------------------------------------------------------

def test_a_file_without_windows_is_explained_by_its_longest_track(tmp_path):
    path = tmp_path / "short.txt"        # two people seen 10 steps, one of them 6
    path.write_text("".join(f"{f} {p} {0.05 * f + p:.3f} {0.3 * p:.3f}\n"
                            for p, steps in ((1, 10), (2, 6)) for f in range(0, 10 * steps, 10)))
    config = DataConfig(scene="short", data=str(path))
    window_set = data.load_split(config, "train")
    assert not len(window_set)
    assert data.no_windows_message(window_set, config, "train") == (
        f"no training windows in short (paper protocol): none of {path} gives one; a window "
        "needs someone detected at 20 steps of 0.4 s (8 s) in a row (8 observed, 12 "
        "predicted), and the longest track is 10 steps (4 s)")
    grid = TimeGrid(obs_len=4, pred_len=4)              # the model's grid decides: 8 steps
    assert len(data.load_split(config, "train", grid)) > 0
    grid = TimeGrid(obs_len=8, pred_len=8)
    assert data.no_windows_message(data.load_split(config, "test", grid), config, "test",
                                   grid).endswith(
        "a window needs someone detected at 16 steps of 0.4 s (6.4 s) in a row (8 observed, 8 "
        "predicted), and the longest track is 10 steps (4 s)")


# --- names ---------------------------------------------------------------------------------

@pytest.mark.parametrize("name, expected", [
    ("cam:1.txt", "cam-1"), ("a<b>|c?.txt", "a-b-c-"), ("-flag.txt", "flag"),
    ("crowd_10hz.txt", "crowd_10hz"),
])
def test_runs_of_own_data_have_names_a_model_name_can_hold(tmp_path, name, expected):
    from gst_jax.io.workdir import run_name

    path = tmp_path / name
    path.write_text(SAMPLE.read_text())
    config = _parsed("--data", str(path), "--fps", "10", "--units", "cm")
    assert config.scene == data.data_name(str(path)) == expected
    name = run_name(config, ModelConfig(), TrainConfig())
    assert ":" not in name and "/" not in name
