"""The project's corpus of bad inputs: each is refused with the file, the line and what is
wrong (or handled correctly), through the readers, make_batch/predict and the commands."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import gst_jax
from gst_jax import data
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import DataError, RunError
from gst_jax.io.workdir import WorkDir
from gst_jax.training.loop import fit
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step


def _walkers(frames, pedestrians: int = 3, origin=(0.0, 0.0)) -> list[str]:
    """`frame ped x y` rows of pedestrians walking 0.5 m per step."""
    return [f"{f} {p} {origin[0] + 0.05 * f + p:.4f} {origin[1] + 0.3 * p:.4f}"
            for f in frames for p in range(1, pedestrians + 1)]


def _write(path: Path, rows: list[str] | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(rows, bytes):
        path.write_bytes(rows)
    else:
        path.write_text("\n".join(rows) + "\n")
    return path


def _command(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          timeout=600)


def _one_line_error(result: subprocess.CompletedProcess) -> str:
    """The command failed with a message of one line and no traceback; returns it."""
    assert result.returncode != 0, result.stdout
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    return lines[-1]


# --- the frame grid -----------------------------------------------------------------------

def test_a_row_off_the_frame_grid_is_refused_with_its_line(tmp_path):
    rows = _walkers(range(0, 300, 10))
    rows.insert(40, "123 1 6.15 0.3")                 # one row off the grid of 10
    path = _write(tmp_path / "off.txt", rows)
    with pytest.raises(DataError, match=rf"{path}:41: frame 123 is off the file's grid "
                                             r"\(every 10 frames from 0\); 1 row\(s\)"):
        data.read_tracks(path)
    with pytest.warns(UserWarning, match=r"dropped 1 row\(s\) off the grid of every 10 frames"):
        tracks = data.read_tracks(path, drop_off_grid=True)
    assert tracks.frame_step == 10 and 123 not in tracks.frames
    assert sum(w is not None for w in data.windows.cut_windows(tracks, 20, 8)) == 11


def test_a_pedestrian_sampled_on_another_phase_is_refused(tmp_path):
    rows = _walkers(range(0, 300, 10)) + [f"{f} 9 1.0 1.0" for f in range(5, 100, 10)]
    path = _write(tmp_path / "phase.txt", rows)
    with pytest.raises(DataError, match=rf"{path}:91: frame 5 is off .* 10 row\(s\)"):
        data.read_tracks(path)


# --- malformed TrajNet++ files ----------------------------------------------------------------

@pytest.mark.parametrize("record, problem", [
    ('{"track": 5}', "'track' is not an object: 5"),
    ('{"track": {"f": 0, "p": 1, "x": true, "y": 0.0}}', "x is not a number: True"),
    ('{"track": {"f": 0, "p": 1, "x": "1.5", "y": 0.0}}', "x is not a number: '1.5'"),
    ('{"track": {"f": 1e20, "p": 1, "x": 1.0, "y": 0.0}}', "frame 1e+20 is too large"),
])
def test_ndjson_values_of_the_wrong_type_are_refused(tmp_path, record, problem):
    good = '{"track": {"f": 0, "p": 2, "x": 0.0, "y": 0.0}}'
    path = _write(tmp_path / "crowd.ndjson", [good, record])
    with pytest.raises(DataError) as error:
        data.read_tracks(path)
    assert str(error.value).startswith(f"{path}:2: ") and problem in str(error.value)


@pytest.mark.parametrize("name, content, column", [
    ("tracks.txt", b"0 1 0.0 0.0\n10 1 \xff 0.0\n", 6),
    ("crowd.ndjson", b'{"track": {"f": 0, "p": 1, "x": 0, "y": 0}}\n{"track": \xff}\n', 11),
])
def test_bytes_that_are_not_utf8_are_refused_with_their_line(tmp_path, name, content, column):
    path = _write(tmp_path / name, content)
    with pytest.raises(DataError,
                       match=rf"{path}:2: not UTF-8 text \(byte 0xff at column {column}\)"):
        data.read_tracks(path)


def test_deeply_nested_ndjson_brackets_are_refused_with_their_line(tmp_path):
    good = '{"track": {"f": 0, "p": 2, "x": 0.0, "y": 0.0}}'
    path = _write(tmp_path / "deep.ndjson", [good, "[" * 100_000])
    with pytest.raises(DataError, match=rf"^{path}:2: not valid JSON \(nested too deeply\)$"):
        data.read_tracks(path)


# --- trackers' CSV files and --columns --------------------------------------------------------

MOT_HEADER = "frame,id,bb_left,bb_top,bb_width,bb_height,conf,x,y,z"
MOT_ROW = "{f},1,-1,-1,-1,-1,1,{x},0.5,0"


@pytest.mark.parametrize("lines, columns, problem", [
    ([MOT_HEADER, MOT_ROW.format(f=10, x=1.0)], "frame,ped,x,y",
     "1: the header (frame, id, bb_left, bb_top, bb_width, bb_height, conf, x, y, z) has no "
     "column 'ped'"),
    (["time,who,x,y", "0,1,0.0,0.5"], None,
     "1: the header (time, who, x, y) names no frame column: none of its columns is named "
     "frame or frame_id; say which columns hold frame, id, x, y with --columns (e.g. "
     "--columns frame,id,x,y or 1,2,8,9)"),
    (["frame,id,px,py", "0,1,0.0,0.5"], None,
     "1: the header (frame, id, px, py) names no x column: none of its columns is named x; say "
     "which columns hold frame, id, x, y with --columns (e.g. --columns frame,id,x,y or "
     "1,2,8,9)"),
    ([MOT_HEADER, MOT_ROW.format(f=10, x=1.0), "20,1,-1,-1,-1"], None,
     "3: expected 10 columns as line 1 has (frame 1, pedestrian id 2, x 8, y 9), found 5: "
     "'20,1,-1,-1,-1'"),
    ([MOT_HEADER, MOT_ROW.format(f=10, x=1.0), MOT_ROW.format(f=20, x="1,5")], "1,2,8,9",
     "3: expected 10 columns as line 1 has (frame 1, pedestrian id 2, x 8, y 9), found 11: "
     "'20,1,-1,-1,-1,-1,1,1,5,0.5,0'"),
    ([MOT_HEADER, MOT_ROW.format(f=10, x=1.0), MOT_ROW.format(f=20, x="n/a")], None,
     "3: x is not a number: 'n/a'"),
    ([MOT_ROW.format(f=10, x=1.0)], "1,2,8,11",
     "1: --columns 1,2,8,11 names column 11, but the line has 10: "
     "'10,1,-1,-1,-1,-1,1,1.0,0.5,0'"),
    (["0,1,0.0,0.5", "10,1,0.5,0.5"], "frame,id,x,y",
     "1: --columns names the column 'frame', but the file has no header line (its first line "
     "holds numbers); number the columns from 1 instead"),
    ([MOT_ROW.format(f=10, x=1.0)], None,
     "1: expected 4 columns (frame ped x y), found 10: '10,1,-1,-1,-1,-1,1,1.0,0.5,0'; a file "
     "with other columns names them with --columns (e.g. --columns 1,2,8,9)"),
    (["0,1,0.5", "10,1,0.6"], None,         # no --columns given: none is named to the user
     "1: expected 4 columns (frame ped x y), found 3: '0,1,0.5'; every row needs a frame, a "
     "pedestrian id, x and y (a file with more columns names these four with --columns, e.g. "
     "--columns 1,2,8,9)"),
])
def test_bad_csv_files_are_refused_with_their_line(tmp_path, lines, columns, problem):
    path = _write(tmp_path / "tracker.csv", lines)
    with pytest.raises(DataError) as error:
        data.read_tracks(path, columns=columns)
    assert str(error.value) == f"{path}:{problem}"


@pytest.mark.parametrize("columns, problem", [
    ("1,2,8", "expected 4 comma-separated columns"),
    ("0,1,7,8", "columns are numbered from 1, got 0"),
    ("1,2,8,8", "names a column twice"),
])
def test_bad_column_maps_are_refused(tmp_path, columns, problem):
    path = _write(tmp_path / "tracker.csv", [MOT_HEADER, MOT_ROW.format(f=10, x=1.0)])
    with pytest.raises(DataError, match=problem):
        data.read_tracks(path, columns=columns)
    assert problem in _one_line_error(_command("gst_jax.data", "stats", "--data", str(path),
                                               "--columns", columns))


def test_columns_for_an_ndjson_file_and_without_data_are_refused(tmp_path):
    path = _write(tmp_path / "crowd.ndjson", ['{"track": {"f": 0, "p": 2, "x": 0.0, "y": 0.0}}'])
    with pytest.raises(DataError, match=rf"^{path}: --columns 1,2,3,4 names the columns of text "
                                        r"files; a TrajNet\+\+ file's are its keys f, p, x, y$"):
        data.read_tracks(path, columns="1,2,3,4")
    assert _one_line_error(_command("gst_jax.data", "stats", "--columns", "1,2,3,4")) == (
        "error: --fps, --units and --columns describe your own files: give them with --data")


# --- coordinates and ids that float32 / int64 cannot hold ------------------------------------

def test_utm_like_coordinates_keep_their_millimetres(tmp_path):
    origin = (4.5e6 + 123.4567, 5.3e6 + 0.0011)
    path = _write(tmp_path / "utm.txt", _walkers(range(0, 200, 10), origin=origin))
    windows = [w for w in data.windows.cut_windows(data.read_tracks(path), 20, 8) if w]
    window = windows[0]
    assert np.all(np.abs(window.positions) < 1e3)                      # relative to its origin
    absolute = window.positions[:, 0].astype(np.float64) + window.origin
    expected = np.array([[origin[0] + 0.05 * f + 1, origin[1] + 0.3] for f in range(0, 200, 10)])
    np.testing.assert_allclose(absolute, expected, rtol=0, atol=1e-3)


def test_a_frame_id_beyond_2_to_the_53_is_refused(tmp_path):
    path = _write(tmp_path / "big.txt", ["0 1 0.0 0.0", "100000000000000000000 1 1.0 0.0"])
    with pytest.raises(DataError, match=rf"{path}:2: frame 1e\+20 is too large"):
        data.read_tracks(path)


# --- files without windows ---------------------------------------------------------------

def _data_dir(tmp_path: Path, files: dict[str, list[str]]) -> Path:
    for name, rows in files.items():
        _write(tmp_path / "data" / "eth_ucy" / "raw" / "eth" / name, rows)
    return tmp_path / "data"


def test_stats_name_files_without_windows_and_training_refuses_to_start(tmp_path):
    data_dir = _data_dir(tmp_path, {"short.txt": _walkers(range(0, 100, 10))})   # 10 frames < 20
    stats = _command("gst_jax.data", "stats", "--scene", "eth", "--data-dir", str(data_dir))
    assert stats.returncode == 0, stats.stderr
    assert f"note: {data_dir}/eth_ucy/raw/eth/short.txt gives eth/train no window" in stats.stdout
    config = DataConfig(scene="eth", data_dir=str(data_dir))
    with pytest.raises(DataError, match=r"no training windows in eth \(paper protocol\): "
                                             r"none of .*short.txt gives one"):
        fit(ModelConfig(), config, TrainConfig(epochs=1), tmp_path / "run")
    assert not (tmp_path / "run").exists()                   # nothing is left behind


def test_train_with_a_malformed_file_prints_one_line_and_leaves_nothing(tmp_path):
    rows = _walkers(range(0, 300, 10))
    rows[7] = "70 2 abc 0.0"
    data_dir = _data_dir(tmp_path, {"bad.txt": rows})
    result = _command("gst_jax.train", "--scene", "eth", "--data-dir", str(data_dir),
                      "--workdir", str(tmp_path / "run"))
    assert _one_line_error(result) == (f"error: {data_dir}/eth_ucy/raw/eth/bad.txt:8: x is not "
                                       "a number: 'abc'")
    assert not (tmp_path / "run").exists()


# --- flags -----------------------------------------------------------------------------------

@pytest.mark.parametrize("flags, problem", [
    (["--epochs", "0"], "--epochs: must be at least 1, got 0"),
    (["--epochs", "-1"], "--epochs: must be at least 1, got -1"),
    (["--batch-size", "0"], "--batch-size: must be at least 1, got 0"),
    (["--checkpoint-every", "0"], "--checkpoint-every: must be at least 1, got 0"),
    (["--learning-rate", "nan"], "--learning-rate: must be a positive number, got nan"),
    (["--learning-rate", "-0.1"], "--learning-rate: must be a positive number, got -0.1"),
    (["--max-train-windows", "-1"], "--max-train-windows: must be 0 or more, got -1"),
    (["--node-dim", "20"], "--node-dim: must be a multiple of 8 (the encoder's heads), got 20"),
])
def test_bad_training_flags_are_refused_before_anything_runs(tmp_path, capsys, flags, problem):
    from gst_jax import train

    with pytest.raises(SystemExit) as exit_:
        train.main([*flags, "--workdir", str(tmp_path / "run")])
    assert exit_.value.code == 2 and problem in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_bad_flags_of_the_commands_are_one_line_errors():
    assert "--epochs: must be at least 1" in _one_line_error(
        _command("gst_jax.train", "--epochs", "0"))
    assert "--samples: must be at least 1" in _one_line_error(
        _command("gst_jax.evaluate", "runs/none", "--samples", "0"))
    assert "no checkpoint in runs/none" in _one_line_error(
        _command("gst_jax.evaluate", "runs/none"))


def test_the_library_refuses_the_same_settings():
    for bad in (dict(epochs=0), dict(batch_size=0), dict(checkpoint_every=0),
                dict(learning_rate=float("nan")), dict(learning_rate=-1.0)):
        with pytest.raises(ValueError, match="must be"):
            TrainConfig(**bad)


# --- make_batch and predict -----------------------------------------------------------------

@pytest.mark.parametrize("steps", [5, 12])
def test_observations_of_another_length_are_refused(steps):
    xy = np.cumsum(np.full((1, steps, 3, 2), 0.4), axis=1)
    with pytest.raises(ValueError, match=rf"observed_xy has {steps} steps; the model observes "
                                         r"the last obs_len = 8"):
        gst_jax.make_batch(xy)


def test_crowds_beyond_the_largest_bucket_get_a_larger_bucket():
    xy = np.cumsum(np.full((1, 8, 130, 2), 0.4), axis=1) + np.arange(130)[None, None, :, None]
    assert gst_jax.make_batch(xy).shape == (1, 8, 160)
    assert data.bucket_size(129, data.TRAINING_BUCKETS) == 136


def test_far_coordinates_and_no_samples_are_refused():
    with pytest.raises(ValueError, match="beyond 1e\\+04 m, where float32 loses millimetres"):
        gst_jax.make_batch(np.full((1, 8, 2, 2), 4.5e6))
    with pytest.raises(ValueError, match="num_samples must be at least 1, got 0"):
        gst_jax.make_predict(ModelConfig(), num_samples=0)


def test_a_batch_of_the_wrong_length_is_refused_by_predict():
    config = ModelConfig()
    predict = gst_jax.make_predict(config, num_samples=1)
    batch = gst_jax.make_batch(np.cumsum(np.full((1, 8, 3, 2), 0.4), axis=1))
    short = batch._replace(**{name: getattr(batch, name)[:, :5]
                              for name in ("positions", "position_mask", "node_mask")})
    with pytest.raises(ValueError, match="the batch has 5 steps; expected 8 observed steps"):
        predict(gst_jax.init_params(config, jax.random.key(0)), jax.random.key(0), short)


# --- training ------------------------------------------------------------------------------

def test_a_nan_learning_rate_is_rejected_by_the_step_not_saved(tmp_path):
    """A NaN learning rate has finite gradients and non-finite new parameters: the step is
    rejected (state unchanged), and no checkpoint of a non-finite state can be written."""

    config = ModelConfig(encoder_layers=1)                  # compiles faster; any depth will do
    window_set = data.load_split(DataConfig(scene="zara1"), "train").subset(range(4))
    step = next(iter(data.training_batches(window_set, batch_size=4)))
    state = create_train_state(config, jax.random.key(0))
    hparams = hparams_for_epoch(config, TrainConfig(), 1).replace(learning_rate=np.float32("nan"))
    before = jax.tree.map(np.asarray, state)
    new_state, metrics = make_train_step(config)(state, jax.random.key(1), step, hparams)
    assert np.isfinite(float(metrics["loss"])) and not bool(metrics["finite"])
    for new, old in zip(jax.tree.leaves(new_state), jax.tree.leaves(before)):
        np.testing.assert_array_equal(new, old)
    poisoned = jax.tree.map(lambda x: x * np.nan, before.params)
    checkpointer = WorkDir(tmp_path).checkpointer()
    with pytest.raises(RunError, match="refusing to save a non-finite training state"):
        checkpointer.save(1, before.replace(params=poisoned), {}, [])
    checkpointer.close()


def test_evaluate_refuses_a_read_only_work_directory_before_computing(tmp_path, monkeypatch):
    from gst_jax.io import workdir as workdirs

    workdir = WorkDir(tmp_path)
    monkeypatch.setattr(workdirs.os, "access", lambda path, mode: False)
    with pytest.raises(RunError, match=f"cannot write in {tmp_path}"):
        workdir.check_writable()
