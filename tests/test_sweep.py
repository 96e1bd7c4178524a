"""Sweeps: member k of the vmapped sweep trains exactly as a single run of its configuration."""

from __future__ import annotations

import io
import json

import chex
import jax
import numpy as np
import pytest

from gst_jax import data
from gst_jax.config import DataConfig, Member, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.graph import drop_partially_detected
from gst_jax.io.workdir import WorkDir
from gst_jax.model import Controls
from gst_jax.progress import Progress
from gst_jax.rollout import rollout
from gst_jax.runs import load_member
from gst_jax.testing.drawn import (
    bar_heights,
    colour_pixels,
    errorbar_data,
    line_data,
    saved_figures,
)
from gst_jax.training import members as sweep_members, sweep
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step

# The members' programs (compiled by these tests only) compile in half the time with one
# encoder layer; how members are vmapped or looped does not depend on the depth.
ONE_LAYER = ModelConfig(encoder_layers=1)


class _Crash(Exception):
    pass


class _CrashAfterEpoch(Progress):
    """Progress that raises once the line of `epoch` is shown (its metrics are written)."""

    def __init__(self, epoch: int, stream):
        super().__init__(stream)
        self.epoch = epoch

    def line(self, text: str) -> None:
        super().line(text)
        if text.startswith(f"epoch {self.epoch} "):
            raise _Crash


def test_vmapped_sweep_members_equal_single_runs_and_results_are_written(tmp_path):
    members = [Member(0, False, 3), Member(2, True, 4)]  # n, F, seed
    config = sweep_members.sweep_model_config(ONE_LAYER, members)
    data_config = DataConfig(scene="zara1")
    train_config = TrainConfig(epochs=4, batch_size=2, seed=3, checkpoint_every=2,
                               max_train_windows=4)
    # A crash after epoch 3's metrics line, whose last checkpoint is epoch 2.
    with pytest.raises(_Crash):
        sweep.fit_sweep(config, data_config, train_config, members, tmp_path,
                        progress=_CrashAfterEpoch(3, io.StringIO()))
    assert [r["epoch"] for r in WorkDir(tmp_path).read_metrics()] == [1, 2, 3]
    log = io.StringIO()
    with saved_figures() as saved:
        results = sweep.fit_sweep(config, data_config, train_config, members, tmp_path,
                                  eval_samples=2, max_eval_windows=3, progress=Progress(log))
    # The resumed sweep writes every epoch once, and shows progress as training does.
    assert [r["epoch"] for r in WorkDir(tmp_path).read_metrics()] == [1, 2, 3, 4]
    # Resumed in the same process, the sweep compiles nothing again: its restored state is
    # placed as the fresh one was.
    assert [r["compiles"] for r in WorkDir(tmp_path).read_metrics()][2:] == [0, 0]
    # Its training time holds the epochs before the crash too (issue 94: a resumed sweep
    # recorded this process's 1.47 s of 63).
    epoch_times = [r["epoch_time_s"] for r in WorkDir(tmp_path).read_metrics()]
    assert sum(epoch_times[:2]) < results["train_time_s"] <= sum(epoch_times)
    shown = log.getvalue()
    assert f"resuming {tmp_path} after epoch 2" in shown
    assert "epoch 3 loss" in shown and "epoch 4 loss" in shown
    assert f"{members[1].name}: AOE" in shown and "(2/2 evaluated)" in shown

    checkpointer = WorkDir(tmp_path).checkpointer(create=False)
    stacked = checkpointer.restore(sweep.initial_states(config, members))[0]
    checkpointer.close()
    train_set = data.load_split(data_config, "train").subset(range(4))
    single_step = make_train_step(config)
    # Jitted: rolled out op by op, the two members' predictions took 51 s of compiling.
    predict = jax.jit(lambda params, batch, controls: rollout(
        params, jax.random.key(5), batch, config, controls, hard=False,
        deterministic=True).displacements)
    for k, member in enumerate(members):
        alone = sweep_members.member_config(config, member)
        state = create_train_state(alone, jax.random.fold_in(jax.random.key(member.seed), 0))
        epoch_losses = []
        for epoch in range(1, train_config.epochs + 1):
            hparams = hparams_for_epoch(alone, train_config, epoch,
                                        fully_detected_only=member.fully_detected_only)
            epoch_key = jax.random.fold_in(jax.random.key(member.seed), epoch)
            losses = []
            for step, batch in enumerate(data.training_batches(
                    train_set, batch_size=2, seed=train_config.seed, epoch=epoch)):
                state, metrics = single_step(state, jax.random.fold_in(epoch_key, step), batch,
                                             hparams)
                losses.append(float(metrics["loss"]))
            epoch_losses.append(np.mean(losses))
        logged = [record["loss"][member.name] for record in map(
            json.loads, (tmp_path / "metrics.jsonl").read_text().splitlines())]
        np.testing.assert_allclose(logged, epoch_losses, rtol=1e-5)
        # vmap reorders float reductions. Where a gradient is exactly 0 in exact arithmetic
        # (e.g. attention key biases: softmax ignores a per-row constant), Adam's normalisation
        # turns that float noise into full-size steps along directions that change no output.
        # So the members are compared by what they predict, and their parameters only to
        # well within the 8 x lr that 8 Adam steps can move them.
        theirs = sweep_members.unstack(stacked.params, k)
        controls = Controls.make(0.5, member.edge_heads, True)
        step = next(iter(data.training_batches(train_set, batch_size=4)))
        batch = drop_partially_detected(step.micro_batches[0], member.fully_detected_only)
        predictions = [predict(p, batch, controls) for p in (state.params, theirs)]
        np.testing.assert_allclose(*predictions, rtol=1e-4, atol=1e-5)
        differences = np.concatenate([np.abs(np.ravel(a - b)) for a, b in zip(
            jax.tree.leaves(state.params), jax.tree.leaves(theirs))])
        assert np.median(differences) < 1e-6 and np.mean(differences > 1e-4) < 0.01
    # The members really differ (the comparisons above would not notice a shared state).
    first, second = (sweep_members.unstack(stacked.params, k) for k in (0, 1))
    assert max(float(np.abs(a - b).max()) for a, b in zip(jax.tree.leaves(first),
                                                          jax.tree.leaves(second))) > 1e-2

    assert {(row["edge_heads"], row["detection"]) for row in results["table"]} == {
        (0, "partial"), (2, "full")}
    assert json.loads((tmp_path / "results.json").read_text())["scene"] == "zara1"
    assert (tmp_path / "results.csv").read_text().startswith("edge_heads,detection")
    assert "| F (full connection) | partial | 1 |" in (tmp_path / "results.md").read_text()
    # The figure draws each detection mode's AOE and FOE (± their spread over seeds).
    cells = {row["detection"]: row for row in results["table"]}
    for ax, metric in zip(saved[tmp_path / "aoe_foe_vs_n.png"].axes, ("aoe", "foe")):
        drawn = errorbar_data(ax)
        assert set(drawn) == {"partial detection", "full detection"}
        for detection, cell in cells.items():
            points, spread = drawn[f"{detection} detection"]
            np.testing.assert_allclose(points[:, 1], [cell[metric]])
            np.testing.assert_allclose(spread, [cell[f"{metric}_std"]])
    assert colour_pixels(tmp_path / "aoe_foe_vs_n.png") > 500

    # A member read back as a single run (what `simulate SWEEP_DIR:MEMBER` uses).
    run = load_member(tmp_path, members[1].name)
    assert (run.model_config.num_edge_heads, run.train_config.fully_detected_only) == (2, True)
    chex.assert_trees_all_equal(run.params, second)
    with pytest.raises(RunError, match="no member 'n9-partial-seed1'"):
        load_member(tmp_path, "n9-partial-seed1")


def _fake_evaluations(aoe_by_member: dict) -> tuple[list, list]:
    members = list(aoe_by_member)
    evaluations = [{"aoe": aoe, "foe": 2 * aoe, "cv_aoe": 1.0, "cv_foe": 2.0}
                   for aoe in aoe_by_member.values()]
    return members, evaluations


def test_summary_quantities_and_cross_dataset_figures(tmp_path):
    """Best n, sparse-vs-full and partial-vs-full improvements from hand-made AOEs."""
    import _figures as figures  # experiments/_figures.py

    M = Member
    all_results = []
    for scene, best in (("zara1", 0.4), ("hotel", 0.2)):
        members, evaluations = _fake_evaluations({
            M(0, False, 1): 0.5, M(0, False, 2): 0.7,      # full connection, partial: 0.6
            M(4, False, 1): best, M(4, False, 2): best,    # n = 4, partial
            M(1, False, 1): 0.55, M(1, False, 2): 0.55,
            M(4, True, 1): 0.5, M(4, True, 2): 0.5})       # n = 4, fully detected only
        window_set = data.load_split(DataConfig(scene=scene), "test").subset(range(5))
        results = sweep.summarize(evaluations, members, DataConfig(scene=scene),
                                  TrainConfig(epochs=1), 2, window_set)
        all_results.append(results)
    zara1 = all_results[0]
    cell = {(r["edge_heads"], r["detection"]): r for r in zara1["table"]}
    assert cell[(0, "partial")]["aoe"] == 0.6 and abs(cell[(0, "partial")]["aoe_std"] - 0.1) < 1e-12
    assert zara1["best_n_partial"] == 4
    sparse_vs_full = zara1["sparse_vs_full_connection_partial"]["aoe_pct"]
    assert abs(sparse_vs_full - 100 * (0.6 - 0.4) / 0.6) < 1e-9
    assert abs(zara1["partial_vs_fully_detected"]["4"]["aoe_pct"] - 100 * (0.5 - 0.4) / 0.5) < 1e-9
    assert zara1["density"] >= 0
    markdown = sweep.format_markdown(zara1).splitlines()
    assert ("Best n (partial detection, by AOE): 4; against full connection: AOE 33.3 % better, "
            "FOE 33.3 % better.") in markdown
    assert ("n = 4: partial against fully detected: AOE 20.0 % better, FOE 20.0 % better."
            in markdown)
    assert (sweep._in_words({"aoe_pct": -10.5, "foe_pct": 0.0})
            == "AOE 10.5 % worse, FOE 0.0 % better")
    with saved_figures() as saved:
        for draw, name in ((figures.errors_against_n_per_seed, "a.png"),
                           (figures.sparse_gain_against_density, "b.png"),
                           (figures.best_n_per_dataset, "c.png")):
            assert colour_pixels(draw(all_results, tmp_path / name)) > 100
    # Fig. 4, a row per scene: the mean over seeds per n (F, 1, 4) and detection mode, every
    # seed a dot, constant velocity dashed.
    for (aoe_ax, foe_ax), best in zip(np.reshape(saved[tmp_path / "a.png"].axes, (2, 2)),
                                      (0.4, 0.2)):
        for ax, scale in ((aoe_ax, 1), (foe_ax, 2)):
            [partial] = line_data(ax, "tab:blue")
            np.testing.assert_allclose(partial, [[0, 0.6 * scale], [1, 0.55 * scale],
                                                 [2, best * scale]])
            [full] = line_data(ax, "tab:orange")
            np.testing.assert_allclose(full, [[2, 0.5 * scale]])
            dots = np.concatenate([c.get_offsets() for c in ax.collections])
            assert sorted(dots[:, 1] / scale) == pytest.approx(
                sorted([0.5, 0.7, 0.55, 0.55, best, best, 0.5, 0.5]))
            [cv] = line_data(ax, "gray")
            np.testing.assert_allclose(cv[:, 1], scale * 1.0)
    # The best n's gain over full connection against density; the best n per scene.
    gains = saved[tmp_path / "b.png"].axes[0]
    dots = np.concatenate([c.get_offsets() for c in gains.collections])
    np.testing.assert_allclose(dots, [[r["density"], gain] for r, gain in zip(
        all_results, (100 * (0.6 - 0.4) / 0.6, 100 * (0.6 - 0.2) / 0.6))])
    assert [list(h) for h in bar_heights(saved[tmp_path / "c.png"].axes[0])] == [[4, 4]]


def test_members_looped_in_one_program_step_as_the_vmapped_members():
    """`member_map` (lax.map over the members) gives the losses and gradients of vmapping
    them (Adam's update divides by the gradients' scale, so the states are compared loosely:
    a gradient of 1e-9 against 1e-8 moves a parameter by the learning rate)."""
    members = [Member(0, False, 3), Member(2, True, 4)]
    config = sweep_members.sweep_model_config(ONE_LAYER, members)
    train_set = data.load_split(DataConfig(scene="zara1"), "train").subset(range(2))
    packed = next(iter(data.training_batches(train_set, batch_size=2, seed=0, epoch=1)))
    hparams = sweep.member_hparams(config, TrainConfig(), members, 1)
    keys = jax.random.split(jax.random.key(5), len(members))
    params = sweep.initial_states(config, members).params
    vmapped = make_train_step(config, members=True, member_map=False).loss_and_grads(
        params, keys, packed, hparams)
    mapped = make_train_step(config, members=True, member_map=True)
    chex.assert_trees_all_close(mapped.loss_and_grads(params, keys, packed, hparams), vmapped,
                                rtol=1e-4, atol=1e-6)
    state, metrics = mapped(sweep.initial_states(config, members), keys, packed, hparams)
    assert bool(np.all(metrics["finite"])) and np.asarray(state.step).tolist() == [1, 1]
