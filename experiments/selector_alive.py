"""Is a model's edge selector alive? (issue 76): the share of valid targets, at each observed
step of each test window, whose edge probabilities give any weight to a person (not only
to the ghost), per scene.

    python experiments/selector_alive.py pretrained:crowd_d --scenes eth zara1

The release's attention underflows where an invalid or padded neighbour's logit dominates
(docs/MODEL.md 2.1): its row of probabilities becomes all zeros, the target then attends to
nobody. Prints a JSON object {scene: {"targets": ..., "alive": share}}.
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from gst_jax import data
from gst_jax.config import CROWD_SCENES, DataConfig
from gst_jax.model import Controls
from gst_jax.rollout import observed_edge_probabilities
from gst_jax.runs import load_model

# One program per batch shape, whichever scene the batch comes from.
PROBABILITIES = jax.jit(observed_edge_probabilities, static_argnums=2)


def alive_share(run, scene: str) -> dict:
    """Over `scene`'s paper test windows: how many (window, observed step, target) are valid,
    and the share of them with a non-zero probability on some person (any active head)."""
    config, controls = run.model_config, Controls.from_config(run.model_config)
    targets = alive = 0
    for batch in data.evaluation_batches(data.load_split(DataConfig(scene=scene), "test")):
        probs = np.asarray(PROBABILITIES(run.params, batch, config, controls))  # (B, T, N, G, N+1)
        on_people = probs[..., :max(config.num_edge_heads, 1), :-1].sum(axis=(-2, -1))
        valid = np.asarray(batch.node_mask)[:, :config.obs_len] > 0
        valid &= np.asarray(batch.scene_mask)[:, None, None] > 0
        targets += int(valid.sum())
        alive += int((valid & (on_people > 0)).sum())
    return {"targets": targets, "alive": alive / max(targets, 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a run directory or pretrained:NAME")
    parser.add_argument("--epoch", type=int, help="checkpoint epoch of a run (default: its own)")
    parser.add_argument("--scenes", nargs="+", default=list(CROWD_SCENES),
                        help="test splits to measure (default: the seven of the general model)")
    args = parser.parse_args()
    run = load_model(args.model, args.epoch)
    print(json.dumps({scene: alive_share(run, scene) for scene in args.scenes}))


if __name__ == "__main__":
    main()
