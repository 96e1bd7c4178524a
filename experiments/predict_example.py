"""Predict from NaN-marked observations, as a robot's planner would.

    python experiments/predict_example.py                       # random parameters
    python experiments/predict_example.py --workdir runs/eth-paper-d-n1-e200-seed1000
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import gst_jax
from gst_jax.runs import load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", default=None,
                        help="a trained run or pretrained:NAME (default: untrained random "
                             "parameters)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sampled futures")
    args = parser.parse_args()

    if args.workdir:
        run = load_model(args.workdir)
        config, params = run.model_config, run.params
    else:
        config = gst_jax.ModelConfig()
        params = gst_jax.init_params(config, jax.random.key(0))

    # Three people seen over the last 8 steps (0.4 s apart); NaN = not detected. The third
    # entered the field of view 1.2 s ago; the second was missed once.
    t = np.arange(8)[:, None]
    observed = np.full((1, 8, 3, 2), np.nan)
    observed[0, :, 0] = np.hstack([0.5 * t, 0 * t])                 # walking right
    observed[0, :, 1] = np.hstack([6 - 0.45 * t, 0.3 + 0 * t])      # walking left, towards 0
    observed[0, 3, 1] = np.nan
    observed[0, 5:, 2] = np.hstack([3 + 0 * t[5:], -3 + 0.4 * t[5:]])  # crossing upwards

    batch = gst_jax.make_batch(observed)
    predict = gst_jax.make_predict(config, num_samples=20)
    prediction = predict(params, jax.random.key(args.seed), batch)

    positions = np.asarray(prediction.positions)            # (20, 1, 12, N, 2)
    for person in range(3):
        mean_end = positions[:, 0, -1, person].mean(axis=0)
        spread = positions[:, 0, -1, person].std(axis=0).mean()
        print(f"person {person}: last seen {observed[0, -1, person]}, in 4.8 s at "
              f"{np.round(mean_end, 2)} (spread over 20 samples {spread:.2f} m)")
    neighbours = np.asarray(prediction.sampled_adjacency)[0, 0, config.obs_len - 1, :3]
    print("graph at the last observed step (rows: target, columns: neighbours + ghost):")
    print(neighbours[:, list(range(3)) + [-1]])


if __name__ == "__main__":
    main()
