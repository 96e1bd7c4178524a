"""Every shipped pretrained model loads and reproduces its recorded fixed-key AOE."""

from __future__ import annotations

import json

import pytest

from gst_jax import load_pretrained, pretrained
from gst_jax.config import CROWD_SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.io.workdir import WorkDir
from gst_jax.pretrained import export
from gst_jax.pretrained.export import check_aoe, check_data_config
from gst_jax.training.loop import fit


def test_at_least_one_model_is_shipped():
    assert pretrained.available()


@pytest.mark.parametrize("name", pretrained.available())
def test_pretrained_model_reproduces_its_recorded_aoe(name):
    meta = pretrained.load_meta(name)
    config, params = load_pretrained(name)
    aoe = check_aoe(config, params, check_data_config(meta))
    assert abs(aoe - meta["check"]["aoe"]) < 1e-3


def test_the_general_model_is_trained_on_crowd_and_shipped_with_its_score_on_every_scene(
        tmp_path, monkeypatch):
    run = tmp_path / "crowd-run"
    fit(ModelConfig(), DataConfig(scene="crowd"), TrainConfig(
        epochs=1, batch_size=4, max_train_windows=4, checkpoint_every=1), run)
    monkeypatch.setattr(export, "ROOT", tmp_path / "shipped")
    with pytest.raises(RunError, match="no test evaluation on eth at epoch 1"):
        export.export(run, "crowd_d")

    for k, scene in enumerate(CROWD_SCENES):    # as `experiments/crowd.py --train` records them
        WorkDir(run).write_evaluation(DataConfig(scene=scene), "test", 1, {"aoe": k}, "")
    meta = json.loads((export.export(run, "crowd_d") / "meta.json").read_text())
    assert meta["data"]["scene"] == "crowd"
    assert {scene: m["aoe"] for scene, m in meta["test_metrics_per_scene"].items()} == {
        scene: k for k, scene in enumerate(CROWD_SCENES)}
