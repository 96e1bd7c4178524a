"""Figures render from a (random, untrained) run directory; nothing is drawn inside jit."""

from __future__ import annotations

import json

import jax
import pytest

from gst_jax import plot
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.io.workdir import WorkDir, run_config
from gst_jax.training.state import create_train_state


@pytest.fixture(scope="module")
def random_run(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("run")
    model, data_config, train_config = ModelConfig(), DataConfig(scene="zara1"), TrainConfig()
    state = create_train_state(model, jax.random.key(0))
    checkpointer = WorkDir(workdir).checkpointer()
    checkpointer.save(1, state, run_config(model, data_config, train_config), [])
    checkpointer.close()
    (workdir / "metrics.jsonl").write_text("".join(
        json.dumps({"epoch": e, "loss": 2.0 / e, "val_aoe": 1.0 / e, "val_foe": 2.0 / e}) + "\n"
        for e in range(1, 4)))
    return workdir


@pytest.mark.parametrize("command", [
    ["scene", "--window", "3", "--samples", "2", "--pdf"],
    ["attention", "--window", "3", "--agent", "1"],
    ["training"],
])
def test_figures_are_written(random_run, tmp_path, command):
    out = tmp_path / f"{command[0]}.png"
    plot.main([command[0], str(random_run), "--out", str(out), *command[1:]])
    assert out.stat().st_size > 10_000
    if "--pdf" in command:
        assert out.with_suffix(".pdf").stat().st_size > 10_000


def test_bad_window_is_a_clear_error(random_run):
    with pytest.raises(SystemExit, match="out of range"):
        plot.main(["scene", str(random_run), "--window", "100000"])
