"""Adding a shipped model: a trained run's parameters, its test evaluation and a fixed-key check."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from gst_jax import data
from gst_jax.config import CROWD, CROWD_SCENES, DataConfig, ModelConfig
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.workdir import run_config
from gst_jax.pretrained import ROOT
from gst_jax.runs import load_run

# The fixed-key check stored with every model: AOE on the first windows of its test split.
CHECK = {"windows": 4, "samples": 2, "seed": 0}


def check_data_config(meta: dict) -> DataConfig:
    """The data of a shipped model's fixed-key check: its own, or the bundled data it names."""
    return DataConfig.from_dict(meta["check"].get("data", meta["data"]))


def check_aoe(config: ModelConfig, params, data_config: DataConfig) -> float:
    """AOE of the fixed-key check (CHECK) on the first windows of the test split."""
    test_set = data.load_split(data_config, "test", config.grid)
    test_set = test_set.subset(range(min(CHECK["windows"], len(test_set))))
    return evaluate_params(params, jax.random.key(CHECK["seed"]), test_set, config,
                           num_samples=CHECK["samples"], with_kde=False,
                           with_baseline=False)["aoe"]


def export(run_path: str | Path, name: str, check_data: DataConfig | None = None) -> Path:
    """Copy a trained run's latest parameters and its evaluation into the package. The
    fixed-key check runs on the run's own data, or on `check_data` where that is not bundled
    (a relative path into the bundled data, so that it is found on any machine)."""
    run = load_run(run_path)
    metrics = run.workdir.read_evaluation(run.data_config, "test", run.epoch)
    per_scene = {}
    if run.data_config.scene == CROWD:    # the general model: its score on every scene
        for scene in CROWD_SCENES:
            config = dataclasses.replace(run.data_config, scene=scene)
            per_scene[scene] = run.workdir.read_evaluation(config, "test", run.epoch)
            if per_scene[scene] is None:
                raise RunError(f"{run.workdir.path} has no test evaluation on {scene} at epoch "
                               f"{run.epoch}: run `python experiments/crowd.py --train` first")
    folder = ROOT / name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    with ocp.StandardCheckpointer() as checkpointer:
        checkpointer.save((folder / "params").absolute(), run.params)
    meta = {**run_config(run.model_config, run.data_config, run.train_config),
            "epoch": run.epoch, "source": str(run.workdir.path), "test_metrics": metrics,
            **({"test_metrics_per_scene": per_scene} if per_scene else {}),
            "train_time_s": run.workdir.training_time_s(), "code": run.workdir.code_versions(),
            "check": {**CHECK, "aoe": check_aoe(run.model_config, run.params,
                                                check_data or run.data_config)}}
    if check_data is not None:
        meta["check"]["data"] = dataclasses.asdict(check_data)
    (folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return folder
