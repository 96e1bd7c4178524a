"""Several devices give one device's results: training, sweeps and evaluation on 4 forced
CPU devices (`--xla_force_host_platform_device_count=4`, so in a subprocess) against 1."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.io.workdir import WorkDir
from gst_jax.runs import load_run
from gst_jax.training.loop import fit

# Runs in a process that sees 4 CPU devices, or in one that sees 1 (argv: 4 or 1, and where
# to save what it measured). The two run side by side: compiling is mostly one thread each.
SCRIPT = textwrap.dedent("""
    import json, sys, tempfile
    import jax, numpy as np
    from gst_jax import data, parallel
    from gst_jax.config import DataConfig, ModelConfig, TrainConfig
    from gst_jax.evaluation import evaluate_params
    from gst_jax.io.workdir import WorkDir
    from gst_jax.runs import load_run
    from gst_jax.training import members as sweep_members, sweep
    from gst_jax.training.loop import fit
    from gst_jax.training.state import create_train_state, hparams_for_epoch, step_key
    from gst_jax.training.step import make_train_step

    def flat(tree):
        return np.concatenate([np.ravel(np.asarray(leaf, np.float64))
                               for leaf in jax.tree.leaves(tree)])

    count, out_path, tmp = int(sys.argv[1]), sys.argv[2], tempfile.mkdtemp()
    assert jax.device_count() == count
    devices = parallel.devices(count) if count > 1 else None
    out = {}
    # One encoder layer: the programs compile faster, the partitioning is the same.
    config, hotel = ModelConfig(encoder_layers=1), DataConfig(scene="hotel")

    # One step of 6 small hotel windows and 3 large ones (> 24 pedestrians observed: univ's
    # smallest crowds).
    train_set = data.load_split(hotel, "train")
    sizes = np.array([w.num_observed for w in train_set.windows])
    large = [w for w in data.load_split(DataConfig(scene="univ"), "test").windows
             if w.num_observed > data.SHARED_MICRO_BATCH_MAX and w.num_pedestrians <= 32][:3]
    chosen = list(np.flatnonzero(sizes <= 16)[:6])
    windows = [train_set[i] for i in chosen] + large
    state = create_train_state(config, jax.random.key(0))
    step = make_train_step(config, devices=devices)
    packed = data.pack_step(windows, chosen + [len(train_set) + k for k in range(3)], 16,
                            step.slots_multiple)
    hparams = step.place(hparams_for_epoch(config, TrainConfig(), 1))
    loss, grads = step.loss_and_grads(step.place(state.params), step.place(step_key(0, 1, 0)),
                                      packed, hparams)
    out.update(step_loss=float(loss), step_grads=flat(grads),
               step_micro_batches=len(packed.micro_batches))

    # Two epochs of one step on hotel's first windows (at most 16 pedestrians: the step's
    # small micro-batch program serves it again, from the compilation cache).
    fit(config, hotel, TrainConfig(epochs=2, batch_size=16, max_train_windows=16,
                                   checkpoint_every=1), f"{tmp}/run", devices=devices)
    run = load_run(f"{tmp}/run")
    out.update(epoch_losses=[r["loss"] for r in run.workdir.read_metrics()],
               params=flat(run.params))

    # A sweep of 4 members (n in {1, 2} x 2 seeds), and its evaluation.
    members = sweep_members.plan_members([1, 2], "partial", [3, 4])
    results = sweep.fit_sweep(sweep_members.sweep_model_config(config, members), hotel,
                              TrainConfig(epochs=1, batch_size=4, seed=3, max_train_windows=4),
                              members, f"{tmp}/sweep", eval_samples=2, max_eval_windows=2,
                              devices=devices)
    losses = WorkDir(f"{tmp}/sweep").read_metrics()[-1]["loss"]
    out.update(sweep_losses=[losses[m.name] for m in members],
               sweep_evaluations=[[r["aoe"], r["foe"]] for r in results["members"]])

    # Evaluation of hotel's largest test windows (a batch of one, padded to four scenes).
    test_set = data.load_split(hotel, "test")
    sizes = np.array([w.num_pedestrians for w in test_set.windows])
    test_set = test_set.subset(np.flatnonzero(sizes == sizes.max()))
    result = evaluate_params(state.params, jax.random.key(5), test_set, config,
                             num_samples=3, devices=devices)
    names = ("aoe", "foe", "min_ade", "min_fde", "kde_nll", "col_i", "col_ii", "cv_aoe")
    out.update(evaluation=[result[n] for n in names], evaluated_pedestrians=result["pedestrians"])
    np.savez(out_path, **{k: np.asarray(v) for k, v in out.items()})
""")


def _relative(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(a))


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> tuple[dict, dict]:
    """(one device, four devices): what SCRIPT measured in each."""
    folder = tmp_path_factory.mktemp("parallel")
    processes = []
    for count in (1, 4):
        environment = {**os.environ, "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")
                       + f" --xla_force_host_platform_device_count={count}"}
        processes.append(subprocess.Popen(
            [sys.executable, "-c", SCRIPT, str(count), str(folder / f"{count}.npz")],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=environment))
    for process in processes:
        _, stderr = process.communicate(timeout=1200)
        assert process.returncode == 0, stderr[-3000:]
    return tuple(dict(np.load(folder / f"{count}.npz")) for count in (1, 4))


def test_a_step_split_over_four_devices_has_one_devices_loss_and_gradients(measured):
    one, four = measured
    # One device: the 6 small windows share a micro-batch, the 3 large train alone; four
    # devices: the large ones go as one group of four slots.
    assert (int(one["step_micro_batches"]), int(four["step_micro_batches"])) == (4, 2)
    assert _relative(one["step_loss"], four["step_loss"]) <= 1e-5
    assert _relative(one["step_grads"], four["step_grads"]) <= 1e-5


def test_two_epochs_on_four_devices_train_as_on_one(measured):
    one, four = measured
    assert _relative(one["epoch_losses"], four["epoch_losses"]) <= 1e-5
    # Parameters (all of them as one vector): Adam divides each gradient by its own size,
    # so gradients that are zero in exact arithmetic (the attention key biases and the
    # selector's logit bias, under softmax's shift invariance) move them by rounding noise
    # alone. One device with another packing of the same steps differs by 3.5e-5 after two
    # epochs (eth, 24 windows); four devices by 5e-5.
    assert _relative(one["params"], four["params"]) <= 1e-4


def test_a_sweep_of_four_members_on_four_devices_equals_one_device(measured):
    one, four = measured
    assert _relative(one["sweep_losses"], four["sweep_losses"]) <= 1e-5
    assert _relative(one["sweep_evaluations"], four["sweep_evaluations"]) <= 1e-5


def test_evaluation_on_four_devices_equals_one_device(measured):
    one, four = measured
    assert int(one["evaluated_pedestrians"]) == int(four["evaluated_pedestrians"]) > 0
    assert _relative(one["evaluation"], four["evaluation"]) <= 1e-5


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_joined_by_jax_distributed_train_as_one(tmp_path):
    """Two CPU processes on 127.0.0.1, one device each, train one run together."""
    # Two steps on zara1's first windows, all small: one micro-batch shape to compile, of a
    # one-layer encoder (three processes compile it at once on CI's two cores).
    flags = ["--scene", "zara1", "--epochs", "1", "--batch-size", "8", "--max-train-windows",
             "16", "--checkpoint-every", "1", "--encoder-layers", "1",
             "--workdir", str(tmp_path / "two")]
    address = f"127.0.0.1:{_free_port()}"
    processes = [subprocess.Popen(
        [sys.executable, "-m", "gst_jax.train", *flags, "--coordinator", address,
         "--num-processes", "2", "--process-id", str(rank)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for rank in (0, 1)]
    one = tmp_path / "one"                  # the same run in this process, meanwhile
    fit(ModelConfig(encoder_layers=1), DataConfig(scene="zara1"), TrainConfig(
        epochs=1, batch_size=8, max_train_windows=16, checkpoint_every=1), one)
    outputs = [p.communicate(timeout=900) for p in processes]
    for process, (_, stderr) in zip(processes, outputs):
        assert process.returncode == 0, stderr[-3000:]
    two_records, one_records = WorkDir(tmp_path / "two").read_metrics(), WorkDir(one).read_metrics()
    assert len(two_records) == 1                               # written by process 0 alone
    assert two_records[0]["loss"] == pytest.approx(one_records[0]["loss"], rel=1e-5)
    flat = [np.concatenate([np.ravel(leaf) for leaf in jax.tree.leaves(load_run(path).params)])
            for path in (tmp_path / "two", one)]
    assert np.linalg.norm(flat[0] - flat[1]) <= 1e-4 * np.linalg.norm(flat[1])


# Elementwise and reduction ops that jaxlib 0.10's XLA:CPU gives YNNPACK on an AMD EPYC: one
# such fusion segfaulted the 4-device sweep above (gst_jax/host_devices.py). On a CPU that
# gives YNNPACK none of them the probe counts 0 either way. argv: the module to import after
# jax ("jax alone": none).
YNNPACK_PROBE = textwrap.dedent("""
    import importlib, os, sys
    import jax, jax.numpy as jnp
    if sys.argv[1] != "jax alone":
        importlib.import_module(sys.argv[1])
    def softmax_total(a, b, scale):
        x = (a + b) * scale
        return jnp.exp(x - x.max(-1, keepdims=True)).sum(-1)
    shape = (1, 4, 8, 2, 9, 9)
    compiled = jax.jit(softmax_total).lower(jnp.ones(shape), jnp.ones(shape), 2.0).compile()
    print(compiled.as_text().count("__ynn_fusion"))
    print(os.environ["XLA_FLAGS"])
""")


def _ynnpack_fusions(*, importing: str, xla_flags: str) -> tuple[int, str]:
    """(YNNPACK fusions in YNNPACK_PROBE's program, XLA_FLAGS as the process ends)."""
    environment = {**os.environ, "XLA_FLAGS": xla_flags}
    output = subprocess.run([sys.executable, "-c", YNNPACK_PROBE, importing], env=environment,
                            capture_output=True, text=True, check=True).stdout.split("\n")
    return int(output[0]), output[1]


# XLA_FLAGS as the tests have them, less the YNNPACK setting and the device count.
FLAGS = " ".join(flag for flag in os.environ.get("XLA_FLAGS", "").split()
                 if "ynn_fusion_type" not in flag and "device_count" not in flag)
FOUR = f"{FLAGS} --xla_force_host_platform_device_count=4"
USERS = f"{FOUR} --xla_cpu_experimental_ynn_fusion_type=eltwise,reduce"


def test_the_devices_module_keeps_ynnpack_to_matrix_products_where_host_devices_are_forced():
    """`gst_jax.parallel`, which every module that trains or evaluates imports (evaluation
    here), sets the flag on import, before anything computes."""
    everything, _ = _ynnpack_fusions(importing="jax alone", xla_flags=FLAGS)
    # One device: XLA's fusions are left alone.
    assert _ynnpack_fusions(importing="gst_jax.parallel", xla_flags=FLAGS) == (everything, FLAGS)
    # Four forced host devices (where the segfault was seen): matrix products only.
    for module in ("gst_jax.parallel", "gst_jax.evaluation"):
        fusions, set_flags = _ynnpack_fusions(importing=module, xla_flags=FOUR)
        assert fusions == 0, module
        assert set_flags == f"{FOUR} --xla_cpu_experimental_ynn_fusion_type=dot", module
    # A user's own setting wins.
    assert _ynnpack_fusions(importing="gst_jax.parallel", xla_flags=USERS) == (
        _ynnpack_fusions(importing="jax alone", xla_flags=USERS)[0], USERS)


def test_a_command_keeps_ynnpack_to_matrix_products_where_host_devices_are_forced(
        monkeypatch):
    """`gst_jax.cli.run`, which every command's main calls before it computes, sets it too:
    also the commands that never import gst_jax.parallel (navigate, simulate, plot)."""
    from gst_jax import cli

    seen = []
    for xla_flags in (FLAGS, FOUR, USERS):
        monkeypatch.setenv("XLA_FLAGS", xla_flags)
        cli.run(lambda args: seen.append(os.environ["XLA_FLAGS"]),
                cli.parser("gst_jax.probe", "A probe."), [])
    assert seen == [FLAGS, f"{FOUR} --xla_cpu_experimental_ynn_fusion_type=dot", USERS]


def test_importing_gst_jax_changes_no_environment_variable():
    """`import gst_jax`, and its public names bound on first use, leave os.environ as it was,
    also in a process that forces host devices (the YNNPACK setting is gst_jax.parallel's and
    the commands')."""
    code = ("import os; before = dict(os.environ); import gst_jax; gst_jax.ModelConfig; "
            "gst_jax.make_predict; print(before == dict(os.environ))")
    for xla_flags in (FLAGS, FOUR):
        output = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                env={**os.environ, "XLA_FLAGS": xla_flags}, check=True).stdout
        assert output.split() == ["True"], xla_flags
