"""Pretrained parameters shipped with the package: `load_pretrained('eth')` -> (config, params).

Each model lives in `gst_jax/pretrained/<scene>_<d|p>/`: `params/` (orbax) and `meta.json`
(the model config, the run's data and training configs, the metrics measured on its test
split, and a small fixed-key check that `tests/test_pretrained.py` reproduces).
`gst_jax.pretrained.export` adds one from a trained run:

    python -m gst_jax.pretrained export runs/eth-paper-d-n1-e200-seed1000 --name eth_d
    python -m gst_jax.pretrained list
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import orbax.checkpoint as ocp

from gst_jax.config import ModelConfig
from gst_jax.model import init_params

ROOT = Path(__file__).parent


def available() -> list[str]:
    """Names of the shipped models, e.g. ['eth_d', 'eth_p']."""
    return sorted(p.name for p in ROOT.iterdir() if (p / "meta.json").exists())


def folder(name: str) -> Path:
    """The folder of a shipped model; 'eth' means GST (D) on eth ('eth_d')."""
    names = available()
    for candidate in (name, f"{name}_d"):
        if candidate in names:
            return ROOT / candidate
    raise KeyError(f"no pretrained model {name!r}; shipped: {', '.join(names) or 'none'}")


def load_meta(name: str) -> dict:
    return json.loads((folder(name) / "meta.json").read_text())


def load_pretrained(name: str):
    """(ModelConfig, params) of a shipped model ('eth' or 'eth_d', 'eth_p', ...)."""
    config = ModelConfig.from_dict(load_meta(name)["model"])
    like = jax.eval_shape(lambda key: init_params(config, key), jax.random.key(0))
    with ocp.StandardCheckpointer() as checkpointer:
        params = checkpointer.restore((folder(name) / "params").absolute(), like)
    return config, params
