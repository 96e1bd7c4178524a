"""A training in a user's hands: stop signals (Ctrl-C, SIGTERM) save exactly where they land
and the rerun continues bit for bit; a stop that the main thread cannot notice (inside an XLA
compilation) still ends the process promptly; two processes never train into one work
directory; a full disk, a lost checksum file or non-finite parameters in a checkpoint are said
in one line, never used silently; a work directory with ':' in its name can be named."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from gst_jax import cli
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import Interrupted, RunError
from gst_jax.io.checkpoints import Checkpointer, _failures_quiet
from gst_jax.io.workdir import WorkDir
from gst_jax.progress import Progress
from gst_jax.runs import load_model, load_run
from gst_jax.training.loop import fit
from gst_jax.training.state import create_train_state

# One encoder layer: what these tests check does not depend on the depth, and the programs
# compile about a fifth faster than the paper's three layers.
MODEL = ModelConfig(encoder_layers=1)
ZARA1 = DataConfig(scene="zara1")
# 12 windows, 4 a step: 3 steps an epoch. Checkpoints only at the end (epoch 3), so that what
# a stop saves is all there is.
RUN = TrainConfig(epochs=3, batch_size=4, max_train_windows=12, checkpoint_every=5)
TINY_RUN = ["--scene", "zara1", "--epochs", "3", "--batch-size", "4", "--max-train-windows",
            "12", "--checkpoint-every", "5", "--encoder-layers", "1"]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("uninterrupted")
    fit(MODEL, ZARA1, RUN, workdir)
    return load_run(workdir)


def _assert_bit_for_bit(workdir: Path, uninterrupted) -> None:
    assert [r["epoch"] for r in WorkDir(workdir).read_metrics()] == [1, 2, 3]
    run = load_run(workdir)
    assert run.epoch == 3
    for x, y in zip(jax.tree.leaves(run.params), jax.tree.leaves(uninterrupted.params)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not (workdir / "interrupted" / "2").exists()       # gone once the run went past it


class _SignalAt(Progress):
    """Progress that sends `signum` to this process when the loop reports `at`."""

    def __init__(self, signum: int, at: str):
        super().__init__(io.StringIO())
        self.signum, self.at = signum, at

    def live(self, text: str) -> None:
        super().live(text)
        if text.startswith(self.at):
            os.kill(os.getpid(), self.signum)


@pytest.fixture
def stops_enabled():
    """Ctrl-C handled here, also where pytest was started in the background of a script
    (which starts it with SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_inside_an_epoch_saves_there_and_the_rerun_continues_bit_for_bit(
        tmp_path, uninterrupted, stops_enabled, signum):
    with pytest.raises(Interrupted) as stopped:
        fit(MODEL, ZARA1, RUN, tmp_path, progress=_SignalAt(signum, "epoch 2/3 step 2/3"))
    name = signal.Signals(signum).name
    assert str(stopped.value) == (f"interrupted ({name}): rerunning the same command continues "
                                  "from epoch 2 at step 2")
    assert not (tmp_path / "checkpoints" / "1").exists()      # no epoch checkpoint was due
    assert [r["epoch"] for r in WorkDir(tmp_path).read_metrics()] == [1]
    resumed = Progress(io.StringIO())
    fit(MODEL, ZARA1, RUN, tmp_path, progress=resumed)
    assert f"resuming {tmp_path} from epoch 2 at step 2" in resumed.stream.getvalue()
    _assert_bit_for_bit(tmp_path, uninterrupted)


def test_a_stop_at_an_epochs_end_and_a_second_stop_after_the_resume(tmp_path, uninterrupted,
                                                                    stops_enabled):
    with pytest.raises(Interrupted, match="continues from epoch 1$"):
        fit(MODEL, ZARA1, RUN, tmp_path, progress=_SignalAt(signal.SIGINT, "epoch 1/3 step 3/3"))
    with pytest.raises(Interrupted, match="continues from epoch 2 at step 1$"):
        fit(MODEL, ZARA1, RUN, tmp_path, progress=_SignalAt(signal.SIGINT, "epoch 2/3 step 1/3"))
    fit(MODEL, ZARA1, RUN, tmp_path)
    _assert_bit_for_bit(tmp_path, uninterrupted)


def test_a_fresh_start_says_so(tmp_path):
    progress = Progress(io.StringIO())
    fit(MODEL, ZARA1, dataclasses.replace(RUN, epochs=1), tmp_path, progress=progress)
    assert progress.stream.getvalue().startswith(f"starting fresh: no checkpoint in {tmp_path}")


# `python -m gst_jax.train` as a user's terminal starts it (Ctrl-C enabled), which sends
# itself `signum` at its `at`-th optimiser step, then, with `stuck`, never returns to Python
# code that could notice (as inside an XLA compilation).
_TRAIN_STOPPED = """
import os, resource, signal, sys, threading
from gst_jax import train
from gst_jax.progress import Progress

signal.signal(signal.SIGINT, signal.default_int_handler)
if {file_size_limit}:   # writes beyond it fail with EFBIG (Python ignores SIGXFSZ)
    resource.setrlimit(resource.RLIMIT_FSIZE, ({file_size_limit}, {file_size_limit}))
steps = 0
report_step = Progress.live

def step_then_stop(self, *args):
    global steps
    report_step(self, *args)
    steps += 1
    if steps == {at}:
        os.kill(os.getpid(), {signum})
        if {stuck}:
            threading.Event().wait()

Progress.live = step_then_stop
train.main(sys.argv[1:])
"""


def _train(workdir: Path, *, signum: int = 0, at: int = 0, stuck: bool = False,
           file_size_limit: int = 0) -> subprocess.CompletedProcess:
    """The command above; `file_size_limit`: writes beyond it fail, as on a full disk."""
    script = ["-c", _TRAIN_STOPPED.format(signum=int(signum), at=at, stuck=stuck,
                                          file_size_limit=file_size_limit)]
    return subprocess.run([sys.executable, *script, *TINY_RUN, "--workdir", str(workdir)],
                          capture_output=True, text=True, timeout=600)


def test_the_command_stops_with_130_and_says_what_the_rerun_does(tmp_path, uninterrupted):
    stopped = _train(tmp_path, signum=signal.SIGTERM, at=5)        # epoch 2, step 2
    assert stopped.returncode == 130, stopped.stderr
    last_line = stopped.stderr.strip().splitlines()[-1]
    assert last_line == ("interrupted (SIGTERM): rerunning the same command continues from "
                         "epoch 2 at step 2")
    assert "Traceback" not in stopped.stderr
    rerun = _train(tmp_path)
    assert rerun.returncode == 0, rerun.stderr
    assert f"resuming {tmp_path} from epoch 2 at step 2" in rerun.stderr
    _assert_bit_for_bit(tmp_path, uninterrupted)


def test_a_stop_the_main_thread_cannot_notice_still_ends_the_process(tmp_path):
    stuck = _train(tmp_path, signum=signal.SIGINT, at=2, stuck=True)
    assert stuck.returncode == 130, stuck.stderr
    assert stuck.stderr.strip().splitlines()[-1] == (
        f"interrupted before the next save; rerunning the same command starts fresh in "
        f"{tmp_path}")


def test_two_trainings_never_share_a_work_directory(tmp_path):
    with WorkDir(tmp_path).lock():
        holder = (tmp_path / "lock").read_text().strip()
        second = _train(tmp_path)
    assert holder.startswith(f"process {os.getpid()} on {os.uname().nodename} since ")
    assert second.returncode == 1
    assert second.stderr.strip().splitlines()[-1] == (
        f"error: {tmp_path} is in use by {holder}; wait for it to finish, or stop it, before "
        "training there")
    assert not (tmp_path / "metrics.jsonl").exists()
    # A lock left by a process that died is the kernel's no more: taken over.
    (tmp_path / "lock").write_text("process 1 on elsewhere since 2026-01-01 00:00:00\n")
    with WorkDir(tmp_path).lock():
        assert (tmp_path / "lock").read_text().startswith(f"process {os.getpid()} on ")


def test_a_checkpoint_that_cannot_be_written_is_one_line_and_never_used(tmp_path):
    failed = _train(tmp_path, file_size_limit=64 * 1024)
    assert failed.returncode == 1
    lines = failed.stderr.strip().splitlines()
    assert lines[-1] == (f"error: could not write the checkpoint of epoch 3 to {tmp_path}/"
                         "checkpoints (File too large); nothing half-written is used: rerunning "
                         f"the same command starts fresh in {tmp_path}"), failed.stderr
    assert "Traceback" not in failed.stderr
    assert not load_epochs(tmp_path)
    rerun = _train(tmp_path)
    assert rerun.returncode == 0 and "starting fresh" in rerun.stderr, rerun.stderr


def test_a_writer_thread_still_reporting_the_failure_is_not_heard_after_it(capfd):
    # Orbax's writer threads print the failure in pages of tracebacks; one still writing when
    # the save raises once ended a CI run's one-line error with "RuntimeError: Event loop is
    # closed". Its report goes where the rest went, not to the user's terminal, whether the
    # thread started during the save or before it (orbax's event loop), line by line.
    def report_late(start: threading.Event, seconds_a_line: float):
        start.wait()
        for line in (b"Traceback (most recent call last):\n", b"    self._check_closed()\n",
                     b"RuntimeError: Event loop is closed\n"):
            time.sleep(seconds_a_line)
            os.write(2, line)

    running_before = threading.Event()
    threading.Thread(target=report_late, args=(running_before, 0.3)).start()
    with pytest.raises(OSError), _failures_quiet(then=running_before.set):
        started_during = threading.Event()
        threading.Thread(target=report_late, args=(started_during, 0.1)).start()
        started_during.set()
        raise OSError("File too large")
    time.sleep(1.0)
    assert "Event loop" not in capfd.readouterr().err


def test_a_config_that_cannot_be_written_is_one_line(tmp_path):
    failed = _train(tmp_path, file_size_limit=512)
    assert failed.returncode == 1
    assert failed.stderr.strip().splitlines()[-1] == (
        f"error: {tmp_path}/config.json: File too large")


def load_epochs(workdir: Path) -> list[int]:
    folder = workdir / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit())


# --- checkpoints that cannot be verified, or hold non-finite arrays ---

def _saved_epochs(folder: Path, epochs=(1, 2)):
    state = create_train_state(MODEL, jax.random.key(0))
    checkpointer = Checkpointer(folder)
    for epoch in epochs:
        checkpointer.save(epoch, state, {"run": "a"}, [{"epoch": e} for e in range(1, epoch + 1)])
    return checkpointer, state


def test_a_checkpoint_without_a_checksum_is_said_unverified_and_recorded(tmp_path):
    checkpointer, state = _saved_epochs(tmp_path)
    checksums = tmp_path / "checksums.json"
    recorded = json.loads(checksums.read_text())
    checksums.write_text(json.dumps({"1": recorded["1"]}))     # saved, then a crash
    with pytest.warns(UserWarning, match=rf"{tmp_path}/2 has no recorded checksum .* cannot be "
                                         "verified; its arrays are finite and it is used"):
        assert checkpointer.restore(state).epoch == 2
    assert json.loads(checksums.read_text()) == recorded      # verified from now on
    checkpointer.close()


@pytest.mark.parametrize("damage", ["{garbled", '{"2": 5}', "a folder"])
def test_a_damaged_checksums_file_verifies_nothing_and_blesses_nothing(tmp_path, damage):
    """Issue 94: with checksums.json unreadable, a damaged checkpoint was used and its checksum
    recorded, so every later run trusted it. Now nothing is used or recorded: restore refuses,
    naming the file and the way out."""
    checkpointer, state = _saved_epochs(tmp_path)
    checksums = tmp_path / "checksums.json"
    array = max((p for p in (tmp_path / "2").rglob("*") if p.is_file()),
                key=lambda p: p.stat().st_size)
    array.write_bytes(array.read_bytes()[:-8] + bytes(8))      # the newest checkpoint damaged
    if damage == "a folder":
        checksums.unlink()
        checksums.mkdir()
    else:
        checksums.write_text(damage)
    with pytest.raises(RunError, match=r"checksums.json is damaged, so no checkpoint of this run "
                                       "can be verified and none is used: put back a good copy, "
                                       "or delete it"):
        checkpointer.restore(state, fall_back=True)
    assert checksums.is_dir() if damage == "a folder" else checksums.read_text() == damage
    checkpointer.close()


def test_checkpoints_whose_checksums_were_lost_are_never_used(tmp_path):
    """A checkpoint saved over a damaged checksums.json is recorded; those before it are
    recorded as unverifiable and skipped, not blessed."""
    checkpointer, state = _saved_epochs(tmp_path)
    (tmp_path / "checksums.json").write_text("{garbled")
    with pytest.warns(UserWarning, match="checkpoints before epoch 3 can no longer be verified"):
        checkpointer.save(3, state, {"run": "a"}, [{"epoch": e} for e in (1, 2, 3)])
    recorded = json.loads((tmp_path / "checksums.json").read_text())
    assert recorded["1"] == recorded["2"] == "unverifiable" and len(recorded["3"]) == 64
    assert checkpointer.restore(state, fall_back=True).epoch == 3
    checkpointer.discard_after(1)
    with pytest.raises(RunError, match="epoch 1: its checksum was lost"):
        checkpointer.restore(state, fall_back=True)
    checkpointer.close()


def test_non_finite_arrays_in_a_checkpoint_fall_back_to_the_one_before(tmp_path):
    checkpointer, state = _saved_epochs(tmp_path, epochs=(1,))
    poisoned = jax.tree.map(lambda leaf: leaf * np.nan if leaf.dtype == np.float32 else leaf,
                            state)
    manager = ocp.CheckpointManager(tmp_path)                  # past save's finite check
    manager.save(2, args=ocp.args.Composite(
        state=ocp.args.StandardSave(poisoned), config=ocp.args.JsonSave({"run": "a"}),
        metrics=ocp.args.JsonSave([{"epoch": 1}, {"epoch": 2}])))
    manager.wait_until_finished()
    manager.close()
    checkpointer = Checkpointer(tmp_path)
    with pytest.warns(UserWarning, match="using the checkpoint of epoch 1; skipped epoch 2: its "
                                         "arrays are not all finite"):
        assert checkpointer.restore(state, fall_back=True).epoch == 1
    with pytest.raises(RunError, match="epoch 2: its arrays are not all finite"):
        checkpointer.restore(state, 2)
    checkpointer.close()


def test_a_metrics_line_cut_short_is_skipped_with_a_warning(tmp_path):
    workdir = WorkDir(tmp_path)
    workdir.metrics_path.write_text('{"epoch": 1, "loss": 2.0}\n{"epoch": 2, "lo')
    with pytest.warns(UserWarning, match=r"metrics.jsonl:2: skipped a line that is not complete"):
        assert workdir.read_metrics() == [{"epoch": 1, "loss": 2.0}]
    plotted = subprocess.run([sys.executable, "-m", "gst_jax.plot", "training", str(tmp_path),
                              "--out", str(tmp_path / "training.png")],
                             capture_output=True, text=True, timeout=300)
    assert plotted.returncode == 0, plotted.stderr
    assert "warning: " in plotted.stderr and (tmp_path / "training.png").exists()


def test_a_work_directory_with_a_colon_in_its_name_can_be_named(tmp_path, uninterrupted):
    """`load_model` reads DIR:MEMBER for a sweep's member; a path that exists is a path."""
    renamed = tmp_path / "crowd:10hz-run"
    shutil.copytree(uninterrupted.workdir.path, renamed)
    run = load_model(str(renamed))
    assert run.epoch == 3 and run.name == str(renamed)
    assert cli.model_spec(str(renamed)) == str(renamed.absolute())
    with pytest.raises(RunError, match="no checkpoint in"):
        load_model(str(tmp_path / "missing:member"))
