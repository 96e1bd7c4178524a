"""Files from someone else, and outputs that could destroy something (issue 94): what a model
folder's config.json names are names, not paths (its scene cannot put an evaluation outside
the work directory, its data path is read only as trajectory files, and said); `predict
--out` never replaces its own data or anything but a regular file, and leaves no half file."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from gst_jax import pretrained
from gst_jax.config import DataConfig, TimeGrid
from gst_jax.data.protocols import data_files, default_data_dir, load_split
from gst_jax.errors import DataError
from gst_jax.evaluate import main as evaluate_main
from gst_jax.model import weights
from gst_jax.predict.__main__ import main as predict_main
from gst_jax.prediction_files import write_predictions


def hostile_copy(tmp_path, **data) -> str:
    """pretrained:zara1_d copied, its config's data fields replaced, its checksum recomputed
    (as anyone editing the file would)."""
    folder = tmp_path / "model"
    shutil.copytree(pretrained.folder("zara1_d"), folder)
    config = json.loads((folder / "config.json").read_text())
    config["data"].update(data)
    config[weights.CONFIG_DIGEST] = weights.config_digest(config)
    (folder / "config.json").write_text(json.dumps(config))
    return str(folder)


def refused(main, capsys, *argv) -> tuple[str, str]:
    """A command run in this process that refuses: its one-line message and its stderr."""
    with pytest.raises(SystemExit) as stop:
        main(list(argv))
    return str(stop.value), capsys.readouterr().err


def evaluate(capsys, *argv) -> tuple[str, str]:
    return refused(evaluate_main, capsys, *argv, "--max-windows", "2", "--samples", "2",
                   "--no-kde")


@pytest.mark.parametrize("scene", ["../../../../../../tmp/escape", "/tmp/escape", ".hidden",
                                   "a/b", "-x"])
def test_a_scene_is_a_name_not_a_path(scene):
    with pytest.raises(ValueError, match="scene must be one of"):
        DataConfig(scene=scene)


def test_a_model_whose_config_names_a_path_as_its_scene_is_refused_in_one_line(tmp_path,
                                                                              capsys):
    model = hostile_copy(tmp_path, scene=f"../../../../../../{tmp_path}/escape")
    work = tmp_path / "work"
    message, _ = evaluate(capsys, model, "--workdir", str(work))
    assert message == (
        f"error: {model}/config.json: scene must be one of eth, hotel, univ, zara1, zara2, lcas, "
        f"wildtrack, crowd or a name of your own data (no / or \\, not starting with . or -, at "
        f"most 120 characters), got '../../../../../../{tmp_path}/escape'")
    assert not any(tmp_path.glob("escape*")) and not work.exists()


def test_a_config_nested_deeper_than_json_can_parse_is_refused_in_one_line(tmp_path, capsys):
    """A field nested 100,000 lists deep was a RecursionError with a traceback (issue 94)."""
    model = hostile_copy(tmp_path)
    config = Path(model) / "config.json"
    config.write_text(config.read_text().replace('"scene"', '"deep": ' + "[" * 100_000
                                                 + "]" * 100_000 + ', "scene"', 1))
    message, _ = evaluate(capsys, model)
    assert message == f"error: {config}: not readable (JSON nested too deeply)"


def test_a_data_path_that_is_not_a_trajectory_file_is_never_read(tmp_path, capsys):
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$secret:19000:0:99999:7:::\n")
    with pytest.raises(DataError, match="shadow: not a trajectory file"):
        data_files(str(secret))
    message, said = evaluate(capsys, hostile_copy(tmp_path, data=str(secret), scene="shadow"))
    assert "secret" not in message + said
    assert f"data: {secret} (the model's own, named by its config" in said
    assert message == f"error: {secret}: not a trajectory file (.txt, .csv or .ndjson)"


def test_a_fifo_or_device_is_not_data(tmp_path):
    """Neither is read (a FIFO would hang the reader, /dev/zero fill the memory)."""
    os.mkfifo(tmp_path / "pipe.txt")
    (tmp_path / "zero.txt").symlink_to("/dev/zero")
    for name in ("pipe.txt", "zero.txt"):
        with pytest.raises(DataError, match=f"{name}: not a regular file or a folder"):
            data_files(str(tmp_path / name))


# --- predict --out: never destroys its target, never leaves half a file -----------------------

SAMPLE = ["--data", "samples/crowd_10hz.txt", "--fps", "10", "--units", "cm", "--samples", "2"]


def predict(*argv, script: str = "") -> subprocess.CompletedProcess:
    program = script or "import sys; from gst_jax.predict.__main__ import main; main(sys.argv[1:])"
    return subprocess.run([sys.executable, "-c", program, "pretrained:hotel_d", *SAMPLE, *argv],
                          capture_output=True, text=True, timeout=600)


def test_predict_refuses_an_out_that_is_its_data_or_not_a_regular_file(tmp_path, capsys):
    data = tmp_path / "mine.txt"
    shutil.copy(default_data_dir() / "samples" / "crowd_10hz.txt", data)
    before = data.read_bytes()
    (tmp_path / "folder").mkdir()
    os.mkfifo(tmp_path / "fifo")
    cases = {str(data): f"error: {data} is the data being predicted: --out must name another "
                        "file",
             str(tmp_path / "folder"): f"error: {tmp_path}/folder exists and is not a regular "
                                       "file: --out names the prediction file to write",
             str(tmp_path / "fifo"): f"error: {tmp_path}/fifo exists and is not a regular file: "
                                     "--out names the prediction file to write",
             "/dev/null": "error: /dev/null exists and is not a regular file: --out names the "
                          "prediction file to write",
             str(tmp_path / "no" / "p.ndjson"): f"error: {tmp_path}/no: no such folder for --out"}
    for out, message in cases.items():
        said, _ = refused(predict_main, capsys, "pretrained:hotel_d", "--data", str(data),
                          "--fps", "10", "--units", "cm", "--out", out)
        assert said == message
    assert data.read_bytes() == before and (tmp_path / "folder").is_dir()
    assert stat.S_ISFIFO((tmp_path / "fifo").stat().st_mode)


def test_a_failed_write_leaves_no_partial_file(tmp_path):
    window_set = load_split(DataConfig(scene="zara1"), "test", TimeGrid())

    def failing(error):
        yield from ()
        raise error

    for error in (KeyboardInterrupt(), OSError(28, "No space left on device")):
        with pytest.raises(type(error)):
            write_predictions(tmp_path / "p.ndjson", window_set, failing(error), TimeGrid())
        assert not any(tmp_path.iterdir())


_PREDICT_STUCK = """
import os, signal, sys, threading
from gst_jax import prediction_files
from gst_jax.predict.__main__ import main

signal.signal(signal.SIGINT, signal.default_int_handler)
rows = prediction_files._window_rows

def rows_then_stuck(*args):
    os.kill(os.getpid(), signal.SIGTERM)
    threading.Event().wait()            # as inside an XLA compilation: nothing notices

prediction_files._window_rows = rows_then_stuck
main(sys.argv[1:])
"""


def test_a_stop_that_ends_predict_leaves_no_partial_file(tmp_path):
    stopped = predict("--out", str(tmp_path / "p.ndjson"), script=_PREDICT_STUCK)
    assert stopped.returncode == 130, stopped.stderr
    assert not any(tmp_path.iterdir())
