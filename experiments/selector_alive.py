"""Is a model's edge selector alive? (issues 76, 93): at each observed step of each test
window, per scene, three different things about each valid target's neighbours:

- its **selection probabilities** (the selector's edge probabilities, docs/MODEL.md 2.1 step
  7): `alive`, the share of targets whose selection probabilities give a person any weight
  (not only the ghost);
- its **sampled edges** (the Gumbel draw from those probabilities, sample 0: the arrows and
  black cells of `plot scene`): `drawn`, the shares of targets whose sampled edge goes to
  another valid person, to itself, to the ghost, or to an empty slot (padding, or nobody
  there at that step), and `selection_probability_of_drawn`, the mean selection probability
  of the sampled edges that go to another person (an edge's: the mean over the n heads, as
  `plot scene` gives it);
- the **encoder's weight** on those sampled edges (its attention after the float mask of
  docs/MODEL.md 2.2, mean over layers and heads): `encoder_weight_on_drawn`, its mean over the
  sampled edges that go to another person.

    python experiments/selector_alive.py pretrained:crowd_d --scenes eth zara1

The release's attention underflows where an invalid or padded neighbour's logit dominates
(docs/MODEL.md 2.1): a row of selection probabilities becomes all zeros, ghost included. The
Gumbel draw from such a row is the noise's alone, uniform over every slot, and the encoder
then attends to whom the noise drew. Prints a JSON object {scene: {"targets": ..., "alive":
share, "drawn": {...}, ...}}.
"""

from __future__ import annotations

import argparse
import functools
import json

import jax
import numpy as np

from gst_jax import data
from gst_jax.config import CROWD_SCENES, DataConfig
from gst_jax.model import Controls
from gst_jax.rollout import observed_edge_probabilities, rollout
from gst_jax.runs import load_model

# One program per batch shape, whichever scene the batch comes from.
PROBABILITIES = jax.jit(observed_edge_probabilities, static_argnums=2)
# One rollout of sample 0 (the plot's graphs: key 0 of `make_predict`'s split), with the
# encoder's attention weights.
ROLLOUT = jax.jit(functools.partial(rollout, hard=True, deterministic=True,
                                    return_attention=True), static_argnums=3)


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


def drawn_edges(run, scene: str, seed: int = 0) -> dict:
    """Over `scene`'s paper test windows, sample 0 of seed `seed` (as `plot scene` draws its
    graphs): where each valid target's sampled edges go, the selection probability of those
    to another person, and the encoder's weight on them (mean over layers and heads)."""
    config, controls = run.model_config, Controls.from_config(run.model_config)
    heads, obs_len = max(config.num_edge_heads, 1), config.obs_len
    where = {"person": 0, "itself": 0, "ghost": 0, "empty": 0}
    probability, weight, targets = [], [], 0
    key = jax.random.split(jax.random.key(seed), 20)[0]  # sample 0 of make_predict(K=20)
    for batch in data.evaluation_batches(data.load_split(DataConfig(scene=scene), "test")):
        out = ROLLOUT(run.params, key, batch, config, controls)
        drawn = np.asarray(out.sampled_edges[:, :obs_len, :, :heads])          # (B, T, N, G, L)
        probs = np.asarray(out.edge_probs[:, :obs_len, :, :heads])
        encoder = np.asarray(out.attention[:, :, :obs_len]).mean(axis=(0, 3))   # (B, T, N, L)
        valid = np.asarray(batch.node_mask)[:, :obs_len] > 0                      # (B, T, N)
        valid &= np.asarray(batch.scene_mask)[:, None, None] > 0
        num = valid.shape[-1]
        for b, t, i, g in zip(*np.nonzero(valid[..., None] & (drawn.sum(-1) > 0.5))):
            j = int(drawn[b, t, i, g].argmax())
            kind = ("ghost" if j == num else "itself" if j == i
                    else "person" if valid[b, t, j] else "empty")
            where[kind] += 1
            if kind == "person":
                probability.append(probs[b, t, i, :, j].mean())     # over heads, as the plot
                weight.append(encoder[b, t, i, j])
        targets += int(valid.sum())
    drawn_total = max(sum(where.values()), 1)
    return {"drawn": {kind: count / drawn_total for kind, count in where.items()},
            "selection_probability_of_drawn": float(np.mean(probability)) if probability
            else None,
            "encoder_weight_on_drawn": float(np.mean(weight)) if weight else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", help="a run directory or pretrained:NAME")
    parser.add_argument("--epoch", type=int, help="checkpoint epoch of a run (default: its own)")
    parser.add_argument("--scenes", nargs="+", default=list(CROWD_SCENES),
                        help="test splits to measure (default: the seven of the general model)")
    args = parser.parse_args()
    run = load_model(args.model, args.epoch)
    print(json.dumps({scene: {**alive_share(run, scene), **drawn_edges(run, scene)}
                      for scene in args.scenes}))


if __name__ == "__main__":
    main()
