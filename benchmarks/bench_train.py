"""Training throughput: windows/s over one full epoch of a scene, after compilation.

    python benchmarks/bench_train.py --scene eth [--edge-heads 1] [--epochs 1]
    python benchmarks/bench_train.py --scene univ --max-steps 2   # a long epoch, extrapolated

Compilation (one program per padding bucket met in the epoch) is timed separately. FLOPs
per step come from XLA's cost analysis; achieved GFLOP/s is also given as a fraction of
the matmul peak measured in the same run (bench_peak.py).
"""

from __future__ import annotations

import argparse
import time

import jax

from bench_peak import measure_peak_gflops
from common import flops_of, peak_rss_gib, print_table, record
from gst_jax import data
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step
from gst_jax.config import SCENES, DataConfig, ModelConfig, TrainConfig

# The authors' release on this project's 2-core CPU (issue 5): seconds per training epoch.
RELEASE_EPOCH_S = {"eth": 16.0, "zara1": 43.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="eth", choices=SCENES, help="dataset (default: eth)")
    parser.add_argument("--protocol", default="paper", help="split protocol (default: paper)")
    parser.add_argument("--edge-heads", type=int, default=1, help="n (default: 1)")
    parser.add_argument("--epochs", type=int, default=1, help="timed epochs (default: 1)")
    parser.add_argument("--seed", type=int, default=1000, help="seed (default: 1000)")
    parser.add_argument("--max-steps", type=int, default=0,
                        help="time only the epoch's first k steps and extrapolate the epoch "
                             "(for univ, whose epoch takes many minutes; default: all)")
    args = parser.parse_args()

    model_config = ModelConfig(num_edge_heads=args.edge_heads)
    train_config = TrainConfig(seed=args.seed)
    window_set = data.load_split(DataConfig(scene=args.scene, protocol=args.protocol), "train")
    state = create_train_state(model_config, jax.random.key(args.seed))
    step = jax.jit(make_train_step(model_config), donate_argnums=0)
    hparams = hparams_for_epoch(model_config, train_config, 1)
    key = jax.random.key(0)

    # Compile every bucket shape the timed epochs will meet, and read its cost.
    epochs = range(1, args.epochs + 1)
    batches = [b for e in epochs for b in data.training_batches(
        window_set, batch_size=train_config.batch_size, seed=args.seed, epoch=e)]
    steps_per_run = len(batches)
    batches = batches[:args.max_steps or None]
    compiled, compile_s = {}, 0.0
    for batch in batches:
        if batch.shape not in compiled:
            start = time.perf_counter()
            compiled[batch.shape] = step.lower(state, key, batch, hparams).compile()
            compile_s += time.perf_counter() - start
    flops = sum(flops_of(compiled[b.shape]) for b in batches)

    start = time.perf_counter()
    for index, batch in enumerate(batches):
        state, metrics = step(state, jax.random.fold_in(key, index), batch, hparams)
    jax.block_until_ready(state)
    elapsed = time.perf_counter() - start

    windows = sum(int(b.scene_mask.sum()) for b in batches)
    peak = measure_peak_gflops()
    gflops = flops / elapsed / 1e9
    release = RELEASE_EPOCH_S.get(args.scene)
    per_epoch = steps_per_run / len(batches) / args.epochs   # from the timed steps to an epoch
    epoch_s = elapsed * per_epoch
    row = record("train", scene=args.scene, edge_heads=args.edge_heads, windows=windows,
                 steps=len(batches), extrapolated=len(batches) < steps_per_run,
                 buckets=sorted({b.shape[2] for b in batches}),
                 compile_s=compile_s, epoch_s=epoch_s,
                 windows_per_s=windows / elapsed,
                 speedup_vs_release=(release / epoch_s) if release else None,
                 gflop_per_epoch=flops / 1e9 * per_epoch, gflops=gflops,
                 peak_gflops=peak, fraction_of_peak=gflops / peak, peak_rss_gib=peak_rss_gib())
    print_table([row], ["scene", "windows", "steps", "extrapolated", "buckets", "compile_s",
                        "epoch_s", "windows_per_s",
                        "speedup_vs_release", "gflops", "fraction_of_peak", "peak_rss_gib"])


if __name__ == "__main__":
    main()
