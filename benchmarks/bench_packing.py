"""What computing only who takes part saves: one training step, two layouts, same windows.

    python benchmarks/bench_packing.py --scenes eth univ

The same 16 training windows (drawn with --seed from the scene's train split) as one
optimiser step's loss and gradient, laid out two ways:
- everyone: every pedestrian of a window on every slot at every step, as the release
  computes (windows of up to 24 pedestrians share a micro-batch, larger ones alone);
- packed: the training layout (`gst_jax.data.pack_step`): pedestrians seen only after the
  observation left out, the prediction steps on the predicted pedestrians' slots only.
Both give the same loss (printed). Times are the best of --repeats after compiling.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from common import print_table, record
from gst_jax import data
from gst_jax.config import SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step


def everyone(windows: list, index: list[int]) -> data.PackedStep:
    """Each window with all its pedestrians on all slots (buckets by its full size)."""
    small = [k for k, w in enumerate(windows) if w.num_pedestrians <= data.SHARED_MICRO_BATCH_MAX]
    large = [k for k, w in enumerate(windows) if w.num_pedestrians > data.SHARED_MICRO_BATCH_MAX]
    groups = ([(small, 16)] if small else []) + [([k], 1) for k in large]
    return data.PackedStep(tuple(
        data.pad_windows([windows[k] for k in group], data.bucket_size(
            max(windows[k].num_pedestrians for k in group), data.TRAINING_BUCKETS), slots,
            [index[k] for k in group]) for group, slots in groups), len(windows))


def time_step(step, params, packed: data.PackedStep, hparams, repeats: int) -> dict:
    start = time.perf_counter()
    loss, _ = jax.block_until_ready(step.loss_and_grads(params, jax.random.key(1), packed, hparams))
    first_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(step.loss_and_grads(params, jax.random.key(1), packed, hparams))
        times.append(time.perf_counter() - start)
    return {"step_s": min(times), "first_s": first_s, "loss": float(loss),
            "micro_batches": len(packed.micro_batches)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["eth", "univ"], choices=SCENES)
    parser.add_argument("--seed", type=int, default=0, help="which 16 windows (default: 0)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()

    config = ModelConfig()
    params = create_train_state(config, jax.random.key(0)).params
    hparams = hparams_for_epoch(config, TrainConfig(), 1)
    step = make_train_step(config)
    rows = []
    for scene in args.scenes:
        train_set = data.load_split(DataConfig(scene=scene), "train")
        index = [int(i) for i in np.random.default_rng(args.seed).permutation(len(train_set))[:16]]
        windows = [train_set[i] for i in index]
        for layout, packed in (("everyone", everyone(windows, index)),
                               ("packed", data.pack_step(windows, index))):
            rows.append(record("packing", scene=scene, layout=layout,
                               **time_step(step, params, packed, hparams, args.repeats)))
    print_table(rows, ["scene", "layout", "micro_batches", "first_s", "step_s", "loss"])


if __name__ == "__main__":
    main()
