"""A fine-tuning's choice of epoch: the one, the starting model's 0 included, with the lowest
validation AOE, kept in <workdir>/selected/ (what `gst_jax.runs.load_model` reads), and its
report beside the starting model and constant velocity on the test windows.

`gst_jax.training.loop.fit` fine-tunes (`train_config.init`) from `fine_tuning_state` after
`check_same_layout`, and selects with `Selection` where the protocol has a validation split.
"""

from __future__ import annotations

import contextlib
from typing import Callable

import jax
import jax.numpy as jnp

from gst_jax import data
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.workdir import WorkDir
from gst_jax.parallel import Devices
from gst_jax.predict import make_predict
from gst_jax.runs import Run
from gst_jax.training.state import TrainState, abstract_train_state, make_optimizer, validation_key

# Samples per validation window when a fine-tuning selects its epoch: the paper's 20 runs.
SELECTION_SAMPLES = 20


class Selection:
    """A fine-tuning's model: the epoch, the starting model's 0 included, with the lowest
    validation AOE, kept in <workdir>/selected/ (what `load_model` then reads) with its score
    and the starting model's. Every epoch is scored with the same draws (one key), so that
    epochs differ by their parameters only; the test split is never looked at to choose."""

    def __init__(self, model_config: ModelConfig, data_config: DataConfig,
                 train_config: TrainConfig, workdir: WorkDir, config: dict,
                 devices: Devices | None):
        self.model_config, self.train_config, self.devices = model_config, train_config, devices
        self.workdir, self.config = workdir, config
        self.val_set = data.load_split(data_config, "val", model_config.grid)
        self.predict = make_predict(model_config, num_samples=SELECTION_SAMPLES, with_graph=False)

    def _score(self, params, window_set: data.WindowSet, key: jax.Array) -> dict:
        return evaluate_params(params, key, window_set, self.model_config,
                               num_samples=SELECTION_SAMPLES, with_kde=False,
                               fully_detected_only=self.train_config.fully_detected_only,
                               predict=self.predict, devices=self.devices)

    def _consider(self, epoch: int, state: TrainState) -> dict:
        result = self._score(state.params, self.val_set, validation_key(self.train_config.seed, 0))
        scored = {"epoch": epoch, "val_aoe": result["aoe"], "val_foe": result["foe"]}
        best = self.best()
        if best is None or scored["val_aoe"] < best["val_aoe"]:
            # The starting model's score (None in a selection made before it was kept).
            start = best.get("start") if best else {"val_aoe": scored["val_aoe"],
                                                     "val_foe": scored["val_foe"]}
            with contextlib.closing(self.workdir.selected_checkpointer()) as saved:
                saved.discard()
                saved.save(epoch, state, self.config, [], {**scored, "start": start})
            best = scored
        return {"val_aoe": scored["val_aoe"], "val_foe": scored["val_foe"],
                "selected_epoch": best["epoch"]}

    def best(self) -> dict | None:
        """{"epoch", "val_aoe", "val_foe", "start"} of the model kept so far (start: the
        starting model's {"val_aoe", "val_foe"}), or None."""
        saved = self.workdir.selected_checkpointer(create=False)
        if saved is None:
            return None
        with contextlib.closing(saved):
            return saved.read_json("progress") if saved.latest_epoch is not None else None

    def start(self, init_state: Callable[[], TrainState]) -> None:
        """Score the starting model as epoch 0 (once; a resumed run has it)."""
        if self.best() is None:
            self._consider(0, init_state())

    def after_epoch(self, epoch: int, state: TrainState) -> dict:
        return self._consider(epoch, state)

    def report(self, source: Run, state: TrainState, data_config: DataConfig) -> dict:
        """The selection, and on the test windows (20 runs each, the same draws) the selected
        model, the starting one and constant velocity."""
        best = self.best()
        assert best is not None, "a report follows a selection"
        with contextlib.closing(self.workdir.selected_checkpointer()) as saved:
            selected = saved.restore(jax.eval_shape(lambda: state)).state
        report = {"from": source.name, "selected_epoch": best["epoch"],
                  "val_windows": len(self.val_set), "val_aoe": best["val_aoe"],
                  "val_foe": best["val_foe"]}
        if best.get("start"):
            report.update(start_val_aoe=best["start"]["val_aoe"],
                          start_val_foe=best["start"]["val_foe"])
        test_set = data.load_split(data_config, "test", self.model_config.grid)
        if not len(test_set):
            return report
        key = jax.random.key(0)
        tuned = self._score(selected.params, test_set, key)
        start = self._score(source.params, test_set, key)
        report["test"] = {"windows": len(test_set),
                          "tuned": {"aoe": tuned["aoe"], "foe": tuned["foe"]},
                          "start": {"aoe": start["aoe"], "foe": start["foe"]},
                          "constant_velocity": {"aoe": tuned["cv_aoe"], "foe": tuned["cv_foe"]}}
        return report


def fine_tuning_state(source: Run) -> TrainState:
    """A fresh optimiser on a copy of the parameters of `source` (fine-tuning; the training
    step donates its state, and `source` is scored beside the result)."""
    params = jax.tree.map(jnp.array, source.params)
    return TrainState(params=params, opt_state=make_optimizer().init(params), step=jnp.int32(0))


def check_same_layout(model_config: ModelConfig, source: Run) -> None:
    """Refuse to fine-tune `source` as `model_config` unless their parameters have the same
    arrays (path and shape), as a resume would."""
    expected = jax.tree_util.tree_flatten_with_path(abstract_train_state(model_config).params)[0]
    given = jax.tree_util.tree_flatten_with_path(source.params)[0]
    layout = {jax.tree_util.keystr(path): tuple(leaf.shape) for path, leaf in expected}
    theirs = {jax.tree_util.keystr(path): tuple(leaf.shape) for path, leaf in given}
    if layout != theirs:
        different = sorted(k for k in layout.keys() | theirs.keys()
                           if layout.get(k) != theirs.get(k))
        raise RunError(f"{source.name} has another architecture than this run (e.g. "
                       f"{different[0]}: {theirs.get(different[0])} against "
                       f"{layout.get(different[0])}); fine-tune a model of the same shapes")
