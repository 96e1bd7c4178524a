"""Training: schedule, loss going down, the non-finite guard, and resume after SIGKILL."""

from __future__ import annotations

import dataclasses
import datetime
import gc
import io
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from gst_jax import data
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import NonFiniteError, RunError
from gst_jax.io.checkpoints import Checkpointer
from gst_jax.io.workdir import WorkDir, code_version, run_config, run_name, same_run
from gst_jax.model import heads
from gst_jax.predict import make_predict
from gst_jax.progress import Progress
from gst_jax.runs import load_run
from gst_jax.training.loop import fit
from gst_jax.training.schedules import make_schedule
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step

PAPER = ModelConfig()
# What the training tests check does not depend on the encoder's depth; one layer compiles
# about a fifth faster than the paper's three.
MODEL = ModelConfig(encoder_layers=1)
ZARA1 = DataConfig(scene="zara1")
TINY_RUN = ["--scene", "zara1", "--epochs", "3", "--batch-size", "4", "--max-train-windows",
            "12", "--checkpoint-every", "1", "--encoder-layers", "1"]


# `python -m gst_jax.train` that SIGKILLs itself after `kill_after` optimiser steps.
_KILLED_TRAIN = """
import os, signal, sys
from gst_jax import train
from gst_jax.progress import Progress

steps = 0
report_step = Progress.live          # the training loop reports every optimiser step

def step_then_die(self, *args):
    global steps
    report_step(self, *args)
    steps += 1
    if steps >= {kill_after}:
        os.kill(os.getpid(), signal.SIGKILL)

Progress.live = step_then_die
train.main(sys.argv[1:])
"""


def _train(workdir: Path, kill_after: int = 0) -> subprocess.CompletedProcess:
    command = (["-c", _KILLED_TRAIN.format(kill_after=kill_after)] if kill_after
               else ["-m", "gst_jax.train"])
    return subprocess.run([sys.executable, *command, *TINY_RUN, "--workdir", str(workdir)],
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def fixed_step():
    window_set = data.load_split(ZARA1, "train")
    step = next(iter(data.training_batches(window_set.subset(range(4)), batch_size=4, seed=0,
                                           epoch=1)))
    assert len(step.micro_batches) == 1                     # zara1's first windows are small
    return step


# A run of TINY_RUN's configuration: what a stopped or faulty run, resumed, must equal.
FAULT_RUN = TrainConfig(epochs=3, batch_size=4, max_train_windows=12, checkpoint_every=1)


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("uninterrupted")
    fit(MODEL, ZARA1, FAULT_RUN, workdir)
    return load_run(workdir)


def _poisoned(step: data.PackedStep, scene: int, time: int, pedestrian=slice(None)):
    """The step with a NaN position in its (only) micro-batch."""
    batch = step.micro_batches[0]
    positions = np.array(batch.positions)
    positions[scene, time, pedestrian] = np.nan
    return step._replace(micro_batches=(batch._replace(positions=positions),))


def test_run_names_say_what_differs_from_the_paper_configuration():
    assert run_name(DataConfig(), PAPER, TrainConfig()) == "eth-paper-d-n1-e200-seed1000"
    wide = ModelConfig(output="gaussian", node_dim=64, edge_dim=128, ghost=False)
    assert (run_name(DataConfig(scene="hotel"), wide, TrainConfig(epochs=5, seed=3))
            == "hotel-paper-p-n1-noghost-d64-e5-seed3")


def test_schedule_matches_release():
    config = TrainConfig()
    lrs = [float(hparams_for_epoch(PAPER, config, e).learning_rate) for e in (1, 50, 51, 101, 200)]
    np.testing.assert_allclose(lrs, [1e-3, 1e-3, 3e-4, 9e-5, 2.7e-5], rtol=1e-5)
    taus = [float(hparams_for_epoch(PAPER, config, e).controls.tau) for e in (1, 100, 200)]
    np.testing.assert_allclose(taus, [(1 - 1 / 200) * 0.47 + 0.03, 0.265, 0.03], rtol=1e-5)


def test_compressed_schedule_fits_the_paper_shape_to_the_run():
    def schedule(config):
        return [make_schedule(config).at(e) for e in range(1, config.epochs + 1)]
    assert schedule(TrainConfig(schedule="compressed")) == schedule(TrainConfig())
    short = schedule(TrainConfig(schedule="compressed", epochs=50))
    learning_rates, taus = zip(*short)
    # x0.3 at each quarter of the run: epochs 14, 26 and 39 start a new rate (E/4 = 12.5).
    starts = [e for e in range(2, 51) if learning_rates[e - 1] != learning_rates[e - 2]]
    assert starts == [14, 26, 39]
    np.testing.assert_allclose(learning_rates[-1], 2.7e-5, rtol=1e-6)
    np.testing.assert_allclose([taus[0], taus[24], taus[-1]], [0.5 - 0.47 / 50, 0.265, 0.03],
                               rtol=1e-6)


def test_the_finetune_schedule_holds_its_learning_rate_and_the_end_temperature():
    config = TrainConfig(schedule="finetune", epochs=10, learning_rate=1e-4)
    learning_rates, taus = zip(*(make_schedule(config).at(e) for e in range(1, 11)))
    np.testing.assert_allclose(learning_rates, [1e-4] * 10, rtol=1e-6)
    np.testing.assert_allclose(taus, [0.03] * 10, rtol=1e-6)


def test_the_schedule_is_part_of_a_runs_identity():
    compressed = TrainConfig(schedule="compressed", epochs=50)
    assert run_name(DataConfig(), PAPER, compressed) == "eth-paper-d-n1-compressed-e50-seed1000"
    paper = run_config(PAPER, DataConfig(), TrainConfig(epochs=50))
    assert not same_run(paper, run_config(PAPER, DataConfig(), compressed))
    # A run written before schedules were named trained the paper schedule, and resumes.
    older = json.loads(json.dumps(paper))
    del older["train"]["schedule"]
    assert same_run(older, paper)


def test_loss_goes_down_on_a_fixed_batch(fixed_step):
    state = create_train_state(MODEL, jax.random.key(0))
    step = make_train_step(MODEL, rotate=False)
    hparams = hparams_for_epoch(MODEL, TrainConfig(), epoch=1)
    key = jax.random.key(1)
    losses = []
    for _ in range(16):                    # the last five's mean: 0.26 of the first three's
        state, metrics = step(state, key, fixed_step, hparams)
        losses.append(float(metrics["loss"]))
    assert all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3]), losses


def test_a_new_output_head_is_one_entry_in_the_registry(fixed_step, monkeypatch):
    """A head registered in HEADS trains, predicts and names its runs with nothing else
    changed: here GST with the mean absolute error of positions as its loss."""
    def position_l1(losses: heads.Losses) -> jax.Array:
        mask = losses.step_mask[..., None]
        error = jnp.cumsum((losses.displacements - losses.true_displacements) * mask, axis=1)
        return heads.safe_ratio(jnp.sum(jnp.abs(error) * mask, axis=(1, 2, 3)),
                                jnp.sum(mask, axis=(1, 2, 3)))
    monkeypatch.setitem(heads.HEADS, "l1", heads.Head(
        letter="l1", sampled=False, draw=lambda mu, sigma, corr, normal: mu,
        scene_loss=position_l1))

    config = dataclasses.replace(MODEL, output="l1")
    state = create_train_state(config, jax.random.key(0))
    step = make_train_step(config, rotate=False)
    hparams = hparams_for_epoch(config, TrainConfig(), epoch=1)
    losses = []
    for _ in range(10):                    # the last three's mean: 0.64 of the first
        state, metrics = step(state, jax.random.key(1), fixed_step, hparams)
        losses.append(float(metrics["loss"]))
    assert np.mean(losses[-3:]) < 0.7 * losses[0], losses
    assert (run_name(DataConfig(), dataclasses.replace(PAPER, output="l1"), TrainConfig())
            == "eth-paper-l1-n1-e200-seed1000")
    batch = fixed_step.micro_batches[0]
    prediction = make_predict(config, num_samples=2)(state.params, jax.random.key(2), batch)
    predicted = np.asarray(prediction.predicted_mask) > 0
    positions = np.moveaxis(np.asarray(prediction.positions), 2, 3)        # (K, B, N, P, 2)
    assert predicted.any() and np.isfinite(positions[:, predicted]).all()
    with pytest.raises(ValueError, match="output 'l2': expected one of deterministic, "
                                         "gaussian, l1"):
        create_train_state(dataclasses.replace(MODEL, output="l2"), jax.random.key(0))


def test_a_packed_step_equals_the_same_windows_in_one_padded_batch():
    """docs/MODEL.md 3: micro-batches padded to their own buckets, their gradients summed
    (or, as on a GPU, one micro-batch padded beyond the largest), give the loss and gradients
    of the same windows, with the same random draws (rotation, Gumbel noise, dropout),
    computed in one batch padded to the largest."""
    small = list(data.load_split(ZARA1, "test").windows[:5])
    large = [w for w in data.load_split(DataConfig(scene="univ"), "test").windows
             if w.num_observed > data.SHARED_MICRO_BATCH_MAX and w.num_pedestrians <= 32][:3]
    windows, index = small + large, [11, 3, 7, 0, 5, 2, 9, 4]
    packed = data.pack_step(windows, index, shared_slots=8)
    # The packed step leaves out who is seen only after the observation and predicts on the
    # predicted pedestrians' slots; the padded batch computes everyone on all 32 slots.
    assert [b.shape[::2] + b.predicted_slots.shape[1:] for b in packed.micro_batches] == [
        (8, 8, 8), (1, 32, 24), (1, 32, 24), (1, 32, 24)]
    assert any(w.num_observed < w.num_pedestrians for w in large)
    padded = data.PackedStep((data.pad_windows(windows, 32, 8, index),), 8)
    # The GPU's packing: one micro-batch of observed pedestrians only, padded to 40 slots.
    one_batch = data.pack_step(windows, index, shared_slots=8, pad_to=40)
    assert [b.shape[::2] + b.predicted_slots.shape[1:] for b in one_batch.micro_batches] == [
        (8, 40, 40)]
    step = make_train_step(MODEL)                        # rotation, dropout, soft samples
    assert not step.one_micro_batch                      # a CPU trains on size buckets
    params = create_train_state(MODEL, jax.random.key(0)).params
    hparams = hparams_for_epoch(MODEL, TrainConfig(), epoch=3)
    (loss, grads), (loss_one, grads_one), (loss_padded, grads_padded) = (
        step.loss_and_grads(params, jax.random.key(1), s, hparams)
        for s in (packed, one_batch, padded))
    for loss_, grads_ in ((loss, grads), (loss_one, grads_one)):
        np.testing.assert_allclose(loss_, loss_padded, rtol=1e-5)
        flat, flat_padded = (np.concatenate([np.ravel(g) for g in jax.tree.leaves(t)])
                             for t in (grads_, grads_padded))
        assert np.linalg.norm(flat - flat_padded) <= 1e-5 * np.linalg.norm(flat_padded)
        # float32 sums in another order differ by a few ulps of the largest terms, so an
        # element that nearly cancels needs an absolute tolerance on its leaf's scale (and
        # 1e-7 at least, for a leaf whose gradient is zero up to rounding).
        for leaf, leaf_padded in zip(jax.tree.leaves(grads_), jax.tree.leaves(grads_padded)):
            atol = max(1e-7, 1e-5 * float(np.max(np.abs(leaf_padded))))
            np.testing.assert_allclose(leaf, leaf_padded, rtol=1e-4, atol=atol)
    # The draws are per window: another key gives another loss.
    other, _ = step.loss_and_grads(params, jax.random.key(2), packed, hparams)
    assert abs(float(other) - float(loss)) > 1e-4


def test_the_last_train_step_is_kept_however_its_arguments_are_spelled():
    """A test or notebook that calls `make_train_step(config)` after `fit` (which names every
    argument) gets fit's step and its traced programs, not a second tracing."""
    kept = make_train_step(MODEL, rotate=True, devices=None)
    assert make_train_step(MODEL) is kept
    assert make_train_step(MODEL, rotate=False) is not kept


def test_non_finite_step_keeps_parameters(fixed_step):
    state = create_train_state(MODEL, jax.random.key(0))
    fully_detected = np.argmax(fixed_step.micro_batches[0].node_mask[0].min(0))
    poisoned = _poisoned(fixed_step, 0, 3, fully_detected)
    step = make_train_step(MODEL, rotate=False)
    hparams = hparams_for_epoch(MODEL, TrainConfig(), epoch=1)
    before = jax.tree.map(np.asarray, state)               # the step donates its state
    new_state, metrics = step(state, jax.random.key(1), poisoned, hparams)
    assert not bool(metrics["finite"])
    for new, old in zip(jax.tree.leaves(new_state.params), jax.tree.leaves(before.params)):
        np.testing.assert_array_equal(new, old)
    assert int(new_state.step) == int(before.step)


def test_fit_stops_on_non_finite_and_names_the_batch(tmp_path, fixed_step, monkeypatch):
    poisoned = _poisoned(fixed_step, slice(None), slice(None))
    monkeypatch.setattr(data, "training_batches", lambda *a, **k: iter([fixed_step, poisoned]))
    config = TrainConfig(epochs=2, batch_size=8, max_train_windows=8, checkpoint_every=1)
    with pytest.raises(NonFiniteError, match="epoch 1, batch 1"):
        fit(MODEL, ZARA1, config, tmp_path / "run")
    assert not (tmp_path / "run" / "checkpoints" / "1").exists()


def test_resume_after_sigkill_matches_uninterrupted_run_and_evaluates(tmp_path, uninterrupted):
    # 12 windows / 4 per step = 3 steps per epoch: killing after step 5 is mid-epoch 2.
    killed = _train(tmp_path / "resumed", kill_after=5)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert (tmp_path / "resumed" / "checkpoints" / "1").exists()
    assert not (tmp_path / "resumed" / "checkpoints" / "2").exists()
    resumed = _train(tmp_path / "resumed")
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stderr

    # The uninterrupted run: TINY_RUN's configuration, trained in this process.
    run = load_run(tmp_path / "resumed")
    assert run.epoch == uninterrupted.epoch == 3
    for x, y in zip(jax.tree.leaves(run.params), jax.tree.leaves(uninterrupted.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)
    metrics = (tmp_path / "resumed" / "metrics.jsonl").read_text().splitlines()
    epochs = [json.loads(line)["epoch"] for line in metrics]
    assert epochs == [1, 2, 3]

    evaluated = subprocess.run(
        [sys.executable, "-m", "gst_jax.evaluate", str(tmp_path / "resumed"), "--samples", "4",
         "--json"], capture_output=True, text=True, timeout=600)
    assert evaluated.returncode == 0, evaluated.stderr
    result = json.loads(evaluated.stdout)
    assert result["windows"] == 124 and result["samples"] == 4
    for name in ("aoe", "foe", "min_ade", "min_fde", "kde_nll", "cv_aoe", "cv_foe"):
        assert np.isfinite(result[name]), name
    assert result["min_ade"] <= result["aoe"]
    assert list((tmp_path / "resumed" / "eval").glob("*.json"))


def test_validation_split_is_evaluated_during_training(tmp_path):
    config = TrainConfig(epochs=2, batch_size=4, max_train_windows=4, eval_every=1,
                         checkpoint_every=2)
    fit(MODEL, DataConfig(scene="hotel", protocol="paper-val"), config, tmp_path / "run")
    records = WorkDir(tmp_path / "run").read_metrics()       # metrics.jsonl and timings.jsonl
    assert [r["epoch"] for r in records] == [1, 2]
    assert all(r["val_aoe"] > 0 and r["val_foe"] >= r["val_aoe"] * 0.5 for r in records)
    finished = [datetime.datetime.strptime(r["finished_at"], "%Y-%m-%dT%H:%M:%SZ")
                for r in records]
    assert finished == sorted(finished)
    # Every epoch names the code that trained it: this checkout's commit.
    assert WorkDir(tmp_path / "run").code_versions() == [code_version()]
    assert re.fullmatch(r"[0-9a-f]{10}(\+dirty)?|gst_jax \S+", code_version())


def test_a_copied_source_tree_names_the_code_it_was_given(tmp_path):
    shutil.copytree(Path(data.__file__).parents[1], tmp_path / "gst_jax",
                    ignore=shutil.ignore_patterns("pretrained", "__pycache__"))
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "GST_JAX_CODE_VERSION": "8f72101f7e gpu"}
    named = subprocess.run([sys.executable, "-c", "from gst_jax.io.workdir import code_version; "
                            "import gst_jax; print(code_version(), gst_jax.__file__)"],
                           env=env, cwd=tmp_path, capture_output=True, text=True, check=True)
    assert named.stdout.split() == ["8f72101f7e", "gpu", str(tmp_path / "gst_jax" / "__init__.py")]


# --- faults: every kind ends with one metrics line per epoch and the parameters of an ---
# --- uninterrupted run, or a clear refusal. The process "dies" by an exception raised ---
# --- at the exact point (saves are synchronous, so the disk is as a SIGKILL leaves it). ---


class _Killed(BaseException):
    """The training process dies here."""


def test_a_finished_run_leaves_no_lock_and_a_rerun_says_it_is_finished(tmp_path, uninterrupted,
                                                                        capsys):
    from gst_jax import train

    finished = uninterrupted.workdir.path
    assert not (finished / "lock").exists() and not (finished / "interrupted").exists()
    rerun = tmp_path / "rerun"
    shutil.copytree(finished, rerun)
    summary = json.loads((rerun / "summary.json").read_text())
    capsys.readouterr()
    assert fit(MODEL, ZARA1, FAULT_RUN, rerun) == {**summary, "already_finished": True}
    said = capsys.readouterr().err
    assert f"already finished: {rerun} holds all 3 epochs" in said and "resuming" not in said
    assert json.loads((rerun / "summary.json").read_text()) == summary    # not rewritten
    # The command says so too (the same run: TINY_RUN's flags are FAULT_RUN's configuration).
    train.main([*TINY_RUN, "--workdir", str(rerun)])
    assert capsys.readouterr().out.startswith("already trained 3 epochs on 12 windows in ")
    assert sorted(p.name for p in rerun.iterdir()) == sorted(p.name for p in finished.iterdir())


def _kill_at_save(monkeypatch, epoch: int, *, before: bool) -> None:
    """Die at the checkpoint of `epoch`, just before or just after it is written."""
    save = Checkpointer.save

    def save_then_die(self, this_epoch, *args):
        if this_epoch == epoch and before:
            raise _Killed
        save(self, this_epoch, *args)
        if this_epoch == epoch:
            raise _Killed

    monkeypatch.setattr(Checkpointer, "save", save_then_die)


def _assert_like_uninterrupted(workdir: Path, uninterrupted) -> None:
    assert [r["epoch"] for r in WorkDir(workdir).read_metrics()] == [1, 2, 3]
    run = load_run(workdir)
    assert run.epoch == 3
    for x, y in zip(jax.tree.leaves(run.params), jax.tree.leaves(uninterrupted.params)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=1e-6)


@pytest.mark.parametrize("epoch, before", [(1, True), (2, False)])
def test_a_kill_at_a_checkpoint_resumes_with_one_line_per_epoch(tmp_path, monkeypatch,
                                                                 uninterrupted, epoch, before):
    """Before the first checkpoint; after a checkpoint and before its metrics line."""
    with monkeypatch.context() as patched:
        _kill_at_save(patched, epoch, before=before)
        with pytest.raises(_Killed):
            fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    lines = [r["epoch"] for r in WorkDir(tmp_path).read_metrics()]
    assert lines == list(range(1, epoch))              # the dying epoch's line is missing
    fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    _assert_like_uninterrupted(tmp_path, uninterrupted)


def test_a_resumed_run_may_change_its_checkpoint_cadence(tmp_path, monkeypatch, uninterrupted):
    with monkeypatch.context() as patched:
        _kill_at_save(patched, 2, before=False)
        with pytest.raises(_Killed):
            fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    fit(MODEL, ZARA1, dataclasses.replace(FAULT_RUN, checkpoint_every=5), tmp_path)
    _assert_like_uninterrupted(tmp_path, uninterrupted)
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir() if p.is_dir()) == \
        ["1", "2", "3"]
    assert json.loads((tmp_path / "config.json").read_text())["train"]["checkpoint_every"] == 5


@pytest.fixture
def ctrl_c_enabled():
    """Ctrl-C raises KeyboardInterrupt here, also where pytest was started in the background
    of a script (which starts it with SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_a_ctrl_c_during_a_checkpoint_save_takes_effect_once_it_is_complete(tmp_path,
                                                                            monkeypatch,
                                                                            ctrl_c_enabled):
    state = create_train_state(MODEL, jax.random.key(0))
    finish = ocp.CheckpointManager.wait_until_finished

    def interrupted_while_writing(manager):
        os.kill(os.getpid(), signal.SIGINT)
        finish(manager)

    monkeypatch.setattr(ocp.CheckpointManager, "wait_until_finished", interrupted_while_writing)
    checkpointer = Checkpointer(tmp_path / "checkpoints")
    with pytest.raises(KeyboardInterrupt):
        checkpointer.save(1, state, {"run": "a"}, [{"epoch": 1}])
    monkeypatch.undo()
    restored = checkpointer.restore(state)             # complete, and its checksum matches
    checkpointer.close()
    assert (restored.epoch, restored.config, restored.records) == (1, {"run": "a"},
                                                                   [{"epoch": 1}])


def test_an_ignored_ctrl_c_stays_ignored_during_a_checkpoint_save(tmp_path, monkeypatch):
    """Where the process ignores SIGINT (a script's background job), a save leaves it ignored
    while it writes (a Ctrl-C then is not held back to stop it after the write, while SIGTERM
    is) and after it, and completes: its checkpoint restores."""
    state = create_train_state(MODEL, jax.random.key(0))
    finish = ocp.CheckpointManager.wait_until_finished
    while_writing = {}

    def pressed_while_writing(manager):
        while_writing.update({s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)})
        os.kill(os.getpid(), signal.SIGINT)
        finish(manager)

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)      # as in a script's background job
    previous_term = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        monkeypatch.setattr(ocp.CheckpointManager, "wait_until_finished", pressed_while_writing)
        checkpointer = Checkpointer(tmp_path / "checkpoints")
        checkpointer.save(1, state, {"run": "a"}, [{"epoch": 1}])
        monkeypatch.undo()
        assert while_writing[signal.SIGINT] is signal.SIG_IGN
        assert callable(while_writing[signal.SIGTERM])                   # held back
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)
    restored = checkpointer.restore(state)
    checkpointer.close()
    assert (restored.epoch, restored.config, restored.records) == (1, {"run": "a"},
                                                                   [{"epoch": 1}])


class _CtrlCInGarbageCollection(Progress):
    """Progress that presses Ctrl-C once, in epoch 2, while Python runs a garbage-collection
    callback (as JAX's `_xla_gc_callback`), where the KeyboardInterrupt is swallowed."""

    def __init__(self):
        super().__init__(io.StringIO())
        self.pressed = False

    def live(self, text: str) -> None:
        super().live(text)
        if text.startswith("epoch 2/") and not self.pressed:
            self.pressed = True
            gc.callbacks.append(self._press)
            try:
                gc.collect()
            finally:
                gc.callbacks.remove(self._press)

    @staticmethod
    def _press(phase, info):
        os.kill(os.getpid(), signal.SIGINT)
        for _ in range(10):                 # the handler runs here, between bytecodes
            pass


def test_a_ctrl_c_swallowed_in_a_garbage_collection_callback_still_stops_training(
        tmp_path, capsys, uninterrupted, ctrl_c_enabled):
    with pytest.raises(KeyboardInterrupt):
        fit(MODEL, ZARA1, FAULT_RUN, tmp_path, progress=_CtrlCInGarbageCollection())
    assert "Exception ignored" not in capsys.readouterr().err
    assert [r["epoch"] for r in WorkDir(tmp_path).read_metrics()] == [1]
    fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    _assert_like_uninterrupted(tmp_path, uninterrupted)


def _damage(folder: Path, how: str) -> None:
    """Truncate, or flip bytes in the middle of, the largest file of a checkpoint."""
    path = max((p for p in folder.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    content = bytearray(path.read_bytes())
    if how == "truncate":
        del content[len(content) // 2:]
    else:
        middle = len(content) // 2
        content[middle:middle + 4] = bytes(b ^ 0xFF for b in content[middle:middle + 4])
    path.write_bytes(bytes(content))


@pytest.mark.parametrize("how", ["truncate", "flip"])
def test_a_damaged_latest_checkpoint_is_skipped_for_the_one_before(tmp_path, monkeypatch,
                                                                    uninterrupted, how):
    with monkeypatch.context() as patched:
        _kill_at_save(patched, 2, before=False)
        with pytest.raises(_Killed):
            fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    _damage(tmp_path / "checkpoints" / "2", how)
    with pytest.warns(UserWarning, match="using the checkpoint of epoch 1; skipped epoch 2: its "
                                         "files do not match the checksum"):
        fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    _assert_like_uninterrupted(tmp_path, uninterrupted)


def test_no_usable_checkpoint_or_another_configuration_is_a_clear_refusal(tmp_path,
                                                                          monkeypatch):
    with monkeypatch.context() as patched:
        _kill_at_save(patched, 2, before=False)
        with pytest.raises(_Killed):
            fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
    (tmp_path / "config.json").unlink()
    other = dataclasses.replace(FAULT_RUN, learning_rate=2e-3)
    with pytest.raises(RunError, match="holds checkpoints of a run with a different configuration"):
        fit(MODEL, ZARA1, other, tmp_path)
    for epoch in (1, 2):
        _damage(tmp_path / "checkpoints" / str(epoch), "flip")
    with pytest.raises(RunError, match=r"no usable checkpoint in .*: epoch 2: its files do not "
                                       r"match .*; epoch 1: its files do not match"):
        fit(MODEL, ZARA1, FAULT_RUN, tmp_path)
