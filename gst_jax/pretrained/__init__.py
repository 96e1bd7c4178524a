"""Pretrained parameters shipped with the package: `load_pretrained('eth')` -> (config, params).

Each model lives in `gst_jax/pretrained/<scene>_<d|p>/`: `params/` (orbax) and `meta.json`
(the model config, the run's training config, the metrics measured on its test split, and a
small fixed-key check that `tests/test_pretrained.py` reproduces).

    python -m gst_jax.pretrained export runs/eth-paper-d-n1-e200-seed1000 --name eth_d
    python -m gst_jax.pretrained list
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from gst_jax.config import ModelConfig
from gst_jax.model import init_params

ROOT = Path(__file__).parent
# The fixed-key check stored with every model: AOE on the first windows of its test split.
CHECK = {"windows": 4, "samples": 2, "seed": 0}


def available() -> list[str]:
    """Names of the shipped models, e.g. ['eth_d']."""
    return sorted(p.name for p in ROOT.iterdir() if (p / "meta.json").exists())


def _resolve(name: str) -> Path:
    names = available()
    candidates = [name, f"{name}_d"]               # 'eth' means GST (D) on eth
    for candidate in candidates:
        if candidate in names:
            return ROOT / candidate
    raise KeyError(f"no pretrained model {name!r}; shipped: {', '.join(names) or 'none'}")


def load_meta(name: str) -> dict:
    return json.loads((_resolve(name) / "meta.json").read_text())


def load_pretrained(name: str):
    """(ModelConfig, params) of a shipped model ('eth' or 'eth_d', 'eth_p', ...)."""
    folder = _resolve(name)
    meta = json.loads((folder / "meta.json").read_text())
    config = ModelConfig(**meta["model"])
    like = jax.tree.map(ocp.utils.to_shape_dtype_struct, init_params(config, jax.random.key(0)))
    with ocp.StandardCheckpointer() as checkpointer:
        params = checkpointer.restore((folder / "params").absolute(), like)
    return config, params


def check_aoe(config: ModelConfig, params, data_config) -> float:
    """AOE of the fixed-key check (CHECK) on the first windows of the test split."""
    from gst_jax import data
    from gst_jax.evaluate import evaluate_params

    test_set = data.load_split(data_config, "test")
    test_set = test_set.subset(range(min(CHECK["windows"], len(test_set))))
    return evaluate_params(params, config, test_set, jax.random.key(CHECK["seed"]),
                           num_samples=CHECK["samples"], with_kde=False,
                           with_baseline=False)["aoe"]


def export(run_path: str, name: str) -> Path:
    """Copy a trained run's latest parameters and its evaluation into the package."""
    from gst_jax.evaluate import load_run
    from gst_jax.train import run_config, training_time_s

    run = load_run(run_path)
    evaluation = (run.workdir / "eval" / f"{run.data_config.scene}-{run.data_config.protocol}"
                  f"-test-e{run.epoch}.json")
    metrics = json.loads(evaluation.read_text()) if evaluation.exists() else None
    folder = ROOT / name
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    with ocp.StandardCheckpointer() as checkpointer:
        checkpointer.save((folder / "params").absolute(), run.params)
    meta = {**run_config(run.model_config, run.data_config, run.train_config),
            "epoch": run.epoch, "source": str(run.workdir), "test_metrics": metrics,
            "train_time_s": training_time_s(run.workdir),
            "check": {**CHECK, "aoe": check_aoe(run.model_config, run.params, run.data_config)}}
    (folder / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return folder
