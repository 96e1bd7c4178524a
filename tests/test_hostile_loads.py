"""Weights, config files and saved streams from others are read only where they are regular
files within a size bound (issue 94; `gst_jax.regular_files`): a FIFO named model.safetensors,
config.json, args.pickle, epoch_N.pt or a saved stream is refused unread instead of blocking
the read forever, a link to /dev/zero instead of being read until memory runs out, a file past
its bound unread.

Each FIFO here has a writer waiting to open it (`fifo`): a reader that opens it reads nothing
(the writer closes at once), so code that opened it fails these tests instead of hanging them.
What would read without end runs in a child whose heap is capped.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import pickle
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from gst_jax import crowdnav
from gst_jax.errors import DataError, RunError
from gst_jax.model import weights
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.stream import Stream

HEAP_CAP = 512 * 2**20


@contextlib.contextmanager
def fifo(path: Path):
    """A FIFO at `path`, with a writer that closes it as soon as a reader opens it."""
    os.mkfifo(path)
    writer = threading.Thread(target=lambda: os.close(os.open(path, os.O_WRONLY)), daemon=True)
    writer.start()
    try:
        yield path
    finally:
        while writer.is_alive():         # nobody read it: open it, so that the writer ends
            os.close(os.open(path, os.O_RDONLY | os.O_NONBLOCK))
            writer.join(0.01)


def weights_folder(to: Path) -> Path:
    """A copy of a shipped weights folder (model.safetensors, config.json)."""
    return Path(shutil.copytree(weights.shipped_folder("crowdnav_sim"), to))


def not_regular(path: Path, kind: str) -> str:
    return f"{path} is {kind}, not a regular file: refused unread (name the file itself)"


def assert_fifo_and_dev_zero_refused(path: Path, load) -> None:
    """`load()` refuses, unread, a FIFO at `path` and then a link from `path` to /dev/zero;
    `path` is left absent."""
    with fifo(path):
        with pytest.raises(DataError) as refused:
            load()
        assert str(refused.value) == not_regular(path, "a FIFO (named pipe)")
    path.unlink()
    path.symlink_to("/dev/zero")
    with pytest.raises(DataError) as refused:
        load()
    assert str(refused.value) == not_regular(path, "a character device (a link to /dev/zero)")
    path.unlink()


def test_a_fifo_as_weights_or_config_is_refused_unread(tmp_path):
    folder = weights_folder(tmp_path / "safetensors")
    (folder / weights.WEIGHTS_FILE).unlink()
    with fifo(folder / weights.WEIGHTS_FILE) as path:
        for load in (weights.load, load_model):
            with pytest.raises(RunError) as refused:
                load(folder)
            assert str(refused.value) == not_regular(path, "a FIFO (named pipe)")

    folder = weights_folder(tmp_path / "config")
    (folder / weights.CONFIG_FILE).unlink()
    with fifo(folder / weights.CONFIG_FILE) as path:
        with pytest.raises(RunError) as refused:
            weights.load(folder)
        assert str(refused.value) == not_regular(path, "a FIFO (named pipe)")
        (folder / weights.WEIGHTS_FILE).unlink()      # then only its config.json tells
        assert not weights.is_weights(folder)


def crowdnav_checkpoint(root: Path) -> Path:
    """A CrowdNav++ folder whose args.pickle is in range and names epoch_100.pt."""
    folder = root / "checkpoint"
    folder.mkdir(parents=True)
    args = dict(temporal="faster_lstm", embedding_size=64, spatial_num_layers=1,
                spatial_num_heads=8, lstm_hidden_size=64, obs_seq_len=5, pred_seq_len=5,
                ghost=False, num_epochs=100, batch_size=16, lr=1e-3, init_temp=0.5,
                random_seed=1000)
    (folder / "args.pickle").write_bytes(pickle.dumps(argparse.Namespace(**args)))
    return root


def test_a_fifo_or_a_device_as_crowdnav_args_or_checkpoint_is_refused_unread(tmp_path):
    root = crowdnav_checkpoint(tmp_path / "args")
    args = root / "checkpoint" / "args.pickle"
    args.unlink()
    assert_fifo_and_dev_zero_refused(args, lambda: crowdnav.load(root))

    root = crowdnav_checkpoint(tmp_path / "pt")
    pt = root / "checkpoint" / "epoch_100.pt"
    assert_fifo_and_dev_zero_refused(pt, lambda: crowdnav.load(root))


def test_a_config_past_its_bound_is_refused_unread(tmp_path):
    folder = weights_folder(tmp_path / "config")
    config = folder / weights.CONFIG_FILE
    os.truncate(config, 2**20 + 1)          # sparse: nothing written
    with pytest.raises(RunError) as refused:
        weights.load(folder)
    assert str(refused.value) == (f"{config}: 1048577 bytes, more than the 1048576 it may hold "
                                  "(gst_jax.model.weights.MAX_CONFIG_BYTES): refused unread")


# weights.load in a child whose heap is capped, one line per folder.
LOAD_IN_A_CHILD = """
import resource, sys
resource.setrlimit(resource.RLIMIT_DATA, (int(sys.argv[1]), int(sys.argv[1])))
from gst_jax.errors import RunError
from gst_jax.model import weights
for folder in sys.argv[2:]:
    try:
        weights.load(folder)
    except RunError as error:
        print("refused:", error)
    except MemoryError:
        print("MemoryError")
    else:
        print("loaded")
"""


def test_weights_from_dev_zero_or_past_their_bound_are_refused_unread(tmp_path):
    """A link to /dev/zero was read until memory ran out (issue 94), a 1 GiB file whole."""
    zero = weights_folder(tmp_path / "zero")
    (zero / weights.WEIGHTS_FILE).unlink()
    (zero / weights.WEIGHTS_FILE).symlink_to("/dev/zero")
    large = weights_folder(tmp_path / "large")
    os.truncate(large / weights.WEIGHTS_FILE, 2**30 + 1)    # sparse: nothing written
    root = Path(__file__).parents[1]
    env = {**os.environ, "PYTHONPATH": str(root), "OPENBLAS_NUM_THREADS": "1"}
    child = subprocess.run([sys.executable, "-c", LOAD_IN_A_CHILD, str(HEAP_CAP), str(zero),
                            str(large)], cwd=root, env=env, capture_output=True, text=True)
    assert child.returncode == 0, child.stderr[-2000:]
    assert child.stdout.strip().splitlines() == [
        "refused: " + not_regular(zero / weights.WEIGHTS_FILE,
                                  "a character device (a link to /dev/zero)"),
        f"refused: {large / weights.WEIGHTS_FILE}: 1073741825 bytes, more than the 1073741824 "
        "it may hold (gst_jax.model.weights.MAX_WEIGHTS_BYTES): refused unread"]


def test_a_fifo_a_device_or_a_file_past_its_bound_as_a_saved_stream_is_refused_unread(tmp_path):
    """Stream.load (`gst_jax.stream_file.read`) opened a FIFO and waited for a writer; /dev/zero
    it read 8 bytes of (a header of 0 bytes), a 1 GiB file it began to read."""
    stream = Stream(ConstantVelocity(obs_len=8, pred_len=12), step_s=0.4)
    saved = tmp_path / "stream.safetensors"
    assert_fifo_and_dev_zero_refused(saved, lambda: stream.load(saved))
    stream.save(saved)
    os.truncate(saved, 2**30 + 1)                       # sparse: nothing written
    with pytest.raises(DataError) as refused:
        stream.load(saved)
    assert str(refused.value) == (f"{saved}: 1073741825 bytes, more than the 1073741824 it may "
                                  "hold (gst_jax.stream_file.MAX_FILE_BYTES): refused unread")
