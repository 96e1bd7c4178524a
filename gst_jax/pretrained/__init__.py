"""Pretrained parameters shipped with the package: `load_pretrained('eth')` -> (config, params).

Each model lives in `gst_jax/pretrained/<name>/`: `model.safetensors` and `config.json` (the
weights format anyone can load, `gst_jax.model.weights`: the parameters, the model config, the
run's data and training configs, the SHA-256 checked at every load) and `meta.json`, its
record: the same configs, where it came from, its licence and the commands that made it, the
metrics measured on its test split and a small fixed-key check that `tests/test_pretrained.py`
reproduces. A model others made carries their licence beside it (`LICENSE.*`); SOURCES.md
lists where every shipped model came from. `gst_jax.pretrained.export` adds one:

    python -m gst_jax.pretrained export runs/eth-paper-d-n1-e200-seed1000 --name eth_d
    python -m gst_jax.pretrained export pretrained:eth_d --out eth_d   # a copy to hand over
    python -m gst_jax.pretrained list
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax.config import ModelConfig
from gst_jax.model import weights

ROOT = Path(__file__).parent


def available() -> list[str]:
    """Names of the shipped models, e.g. ['eth_d', 'eth_p']."""
    return weights.shipped()


def folder(name: str) -> Path:
    """The folder of a shipped model; 'eth' means GST (D) on eth ('eth_d'). Refuses an
    unknown name with a RunError listing those shipped."""
    return weights.shipped_folder(name)


def load_meta(name: str) -> dict:
    """A shipped model's record (meta.json)."""
    return json.loads((folder(name) / weights.SHIPPED_RECORD).read_text())


def load_pretrained(name: str) -> tuple[ModelConfig, dict]:
    """(ModelConfig, params) of a shipped model ('eth' or 'eth_d', 'eth_p', ...), checked
    against its checksum and its config's parameter layout."""
    loaded = weights.load(folder(name))
    return loaded.model_config, loaded.params


def describe(name: str) -> list[str]:
    """A shipped model in `python -m gst_jax.pretrained list`'s lines: its epoch and test AOE /
    FOE (metres), or '-' and why where its record has none (a model others trained on data
    that is not bundled: its fixed-key check is all that was measured), its AOE / FOE per
    scene for the general model, and its licence."""
    meta = load_meta(name)
    metrics = meta.get("test_metrics")
    if metrics:
        scores = (f"AOE {metrics['aoe']:.3f} FOE {metrics['foe']:.3f} "
                  f"({metrics.get('protocol', 'test split')})")
    else:
        check = meta["check"]
        checked = check.get("data", meta["data"])["scene"]
        scores = (f"AOE - FOE - (no test evaluation recorded: trained on "
                  f"{meta['data']['scene']}; its fixed-key check: AOE {check['aoe']:.3f} on "
                  f"{check['windows']} test windows of {checked}, {check['samples']} samples)")
    lines = [f"{name}: epoch {meta['epoch']}, {scores}"]
    if per_scene := meta.get("test_metrics_per_scene"):      # the general model
        lines.append("  per scene AOE / FOE: " + ", ".join(
            f"{scene} {m['aoe']:.3f} / {m['foe']:.3f}" for scene, m in per_scene.items()))
    if meta.get("licence"):
        lines.append(f"  licence: {meta['licence']}")
    return lines
