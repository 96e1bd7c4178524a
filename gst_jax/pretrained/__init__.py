"""Pretrained parameters shipped with the package: `load_pretrained('eth')` -> (config, params).

Each model lives in `gst_jax/pretrained/<name>/`: `model.safetensors` and `config.json` (the
weights format anyone can load, `gst_jax.model.weights`: the parameters, the model config, the
run's data and training configs, the SHA-256 checked at every load) and `meta.json`, its
record: the same configs, where it came from, its licence and the commands that made it, the
metrics measured on its test split and a small fixed-key check that `tests/test_pretrained.py`
reproduces. A model others made carries their licence beside it (`LICENSE.*`); SOURCES.md
lists where every shipped model came from, its time step and the walking speeds it predicts
sensibly (`SPEED_RANGES`). `gst_jax.pretrained.export` adds one:

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

# Each shipped model's speed range, (lowest, highest) in m/s: the speeds at which straight-line
# walkers, alone and three abreast, in any of 8 directions, on the model's own time grid, are
# predicted (mean mode) to end within 25 % of the distance walked over the horizon and to head
# within 30 degrees of the walk, the longest run of such speeds on a grid of 0.25 to 6 m/s;
# None where no speed passes. Measured by experiments/speed_range.py (results/speed_range.md:
# the rule and every speed; tests/test_pretrained.py checks these against its .json).
# Constant velocity is exact on such walkers at any speed.
SPEED_RANGES: dict[str, tuple[float, float] | None] = {
    "crowd_d": (0.75, 3.25), "crowd_p": (0.75, 1.5),
    "crowdnav_env": (0.25, 2.5), "crowdnav_env_obs8": (0.25, 2.5),
    "crowdnav_env_partial": (0.25, 2.75),
    "crowdnav_sim": (1.0, 1.5),
    "crowdnav_sj": None, "crowdnav_sj_rand": (0.75, 1.0),
    "eth_d": None, "eth_p": None,
    "hotel_d": (0.75, 2.5), "hotel_p": (1.25, 1.75),
    "univ_d": (0.25, 0.5), "univ_p": (0.25, 0.25),
    "zara1_d": (1.25, 1.5), "zara1_p": (1.25, 1.75),
    "zara2_d": None, "zara2_p": (1.0, 1.75),
    "wildtrack_d": (0.75, 1.75),
}


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


def speed_range_text(name: str) -> str:
    """A shipped model's time grid and speed range (`SPEED_RANGES`), in one line: 'time step
    0.4 s, 8 observed + 12 predicted steps; walking speeds predicted sensibly: 0.75-3.25 m/s
    (...)'."""
    grid = ModelConfig.from_dict(load_meta(name)["model"]).grid
    speeds = SPEED_RANGES.get(name, "not measured")
    if isinstance(speeds, tuple):
        low, high = speeds
        speeds = f"{low:g} m/s" if low == high else f"{low:g}-{high:g} m/s"
    elif speeds is None:
        speeds = "none from 0.25 to 6 m/s"
    return (f"time step {grid.step_s:g} s, {grid.obs_len} observed + {grid.pred_len} predicted "
            f"steps; walking speeds predicted sensibly: {speeds} (straight walkers in every "
            "direction: results/speed_range.md)")


def describe(name: str) -> list[str]:
    """A shipped model in `python -m gst_jax.pretrained list`'s lines: its epoch and test AOE /
    FOE (metres), or '-' and why where its record has none (a model others trained on data
    that is not bundled: its fixed-key check is all that was measured), its AOE / FOE per
    scene for the general model, its time step and speed range, and its licence."""
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
    lines.append("  " + speed_range_text(name))
    if meta.get("licence"):
        lines.append(f"  licence: {meta['licence']}")
    return lines
