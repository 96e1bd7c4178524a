"""Training throughput: full epochs of a scene, ours and the authors' release in the same run.

    python benchmarks/bench_train.py --scenes eth zara1 univ
    python benchmarks/bench_train.py --scenes eth --release-dir REL \
        --release-python REL_VENV/bin/python
    python benchmarks/bench_train.py --scenes eth --protocol loo   # leave-one-out, eth held out

Ours: every program of the epoch is compiled first (one micro-batch of each shape; the
compilations are counted and timed), then one whole epoch is timed exactly as the training
loop runs it (packed steps, the loss read back every step). FLOPs are the matrix products
of the jaxpr (benchmarks/common.py): of what runs (padded micro-batches) and of the unpadded
model (every window at its own size). The release (optional, see release.py) is timed over
its first K training windows and projected to its epoch, on the same machine in the same run.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from bench_peak import measure_peak_gflops
from common import matmul_flops, peak_rss_gib, print_table, record
from gst_jax import data
from gst_jax.compiles import count_compiles
from gst_jax.config import SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step, training_loss
from release import time_release


def step_flops(config: ModelConfig, params, hparams, batch: data.SceneBatch) -> float:
    """Matrix-product FLOPs of one micro-batch's loss and gradient."""
    def loss_and_grad(p):
        return jax.value_and_grad(training_loss)(p, jax.random.key(0), batch, config, hparams,
                                                 rotate=True, num_scenes=jnp.float32(1))
    return matmul_flops(loss_and_grad, params)


def window_flops(config: ModelConfig, params, hparams) -> np.polynomial.Polynomial:
    """FLOPs of one window of N pedestrians, all of them computed at every step (as the
    release does), as a function of N: a cubic in N (every product is over N, N + 1 or fixed
    widths), fitted exactly on a few sizes."""
    sizes = np.array([8, 16, 32, 48, 64])
    steps = config.obs_len + config.pred_len
    flops = [step_flops(config, params, hparams, data.SceneBatch(
        np.zeros((1, steps, n, 2), np.float32), *[np.ones((1, steps, n), np.float32)] * 2,
        np.ones(1, np.float32), np.zeros(1, np.int32))) for n in sizes]
    return np.polynomial.Polynomial.fit(sizes, flops, 3)


def program(batch: data.SceneBatch) -> tuple:
    """What a micro-batch's compiled program depends on: (B, T, N) and the predicted slots."""
    return batch.shape + (batch.predicted_slots.shape[-1],)


def time_epoch(scene: str, protocol: str, edge_heads: int, seed: int) -> dict:
    config = ModelConfig(num_edge_heads=edge_heads)
    train_config = TrainConfig(seed=seed)
    window_set = data.load_split(DataConfig(scene=scene, protocol=protocol), "train")
    train_step = make_train_step(config)
    state = create_train_state(config, jax.random.key(seed))
    hparams = hparams_for_epoch(config, train_config, 1)
    steps = list(data.training_batches(window_set, batch_size=train_config.batch_size,
                                       seed=seed, epoch=1))
    shapes = {program(b): b for step in steps for b in step.micro_batches}

    with count_compiles() as compiles:
        start = time.perf_counter()
        for batch in shapes.values():
            state, metrics = train_step(state, jax.random.key(0), data.PackedStep((batch,), 1),
                                        hparams)
        float(metrics["loss"])
        warm_up_s = time.perf_counter() - start

    with count_compiles() as late_compiles:
        start = time.perf_counter()
        for index, step in enumerate(steps):
            state, metrics = train_step(state, jax.random.fold_in(jax.random.key(1), index), step,
                                        hparams)
            float(metrics["loss"])                      # as the loop does, every step
        epoch_s = time.perf_counter() - start

    per_shape = {shape: step_flops(config, state.params, hparams, batch)
                 for shape, batch in shapes.items()}
    executed = sum(per_shape[program(b)] for step in steps for b in step.micro_batches)
    per_window = window_flops(config, state.params, hparams)
    unpadded = float(sum(per_window(w.num_pedestrians) for w in window_set.windows))
    sizes = [w.num_pedestrians for w in window_set.windows]
    return {"scene": scene if protocol == "paper" else f"{scene} ({protocol})",
            "windows": len(window_set), "mean_n": float(np.mean(sizes)),
            "steps": len(steps), "micro_batches": sum(len(s.micro_batches) for s in steps),
            "programs": len(shapes), "compiles": compiles.count,
            "compile_s": compiles.seconds, "warm_up_s": warm_up_s,
            "compiles_in_epoch": late_compiles.count, "epoch_s": epoch_s,
            "windows_per_s": len(window_set) / epoch_s,
            "gflop_executed": executed / 1e9, "gflop_unpadded": unpadded / 1e9,
            "gflops_executed": executed / epoch_s / 1e9,
            "gflops_unpadded": unpadded / epoch_s / 1e9}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=["eth"], choices=SCENES)
    parser.add_argument("--protocol", default="paper", help="split protocol (default: paper)")
    parser.add_argument("--edge-heads", type=int, default=1, help="n (default: 1)")
    parser.add_argument("--seed", type=int, default=1000, help="seed (default: 1000)")
    parser.add_argument("--release-dir", default=None,
                        help="a prepared copy of the authors' release (release.py): time it too")
    parser.add_argument("--release-python", default=None, help="the python of its venv")
    parser.add_argument("--release-windows", type=int, default=64,
                        help="training windows the release is timed on (default: 64)")
    parser.add_argument("--release-threads", type=int, default=2)
    args = parser.parse_args()

    peak = measure_peak_gflops()
    rows = []
    for scene in args.scenes:
        row = time_epoch(scene, args.protocol, args.edge_heads, args.seed)
        if args.release_dir and args.protocol == "paper":
            release = time_release(args.release_dir, args.release_python, scene,
                                   windows=args.release_windows,
                                   threads=args.release_threads)["train"]
            row.update(release_epoch_s=release["projected_s"],
                       release_windows_timed=release["windows_timed"],
                       speedup_vs_release=release["projected_s"] / row["epoch_s"])
        row.update(peak_gflops=peak, fraction_of_peak_executed=row["gflops_executed"] / peak,
                   fraction_of_peak_unpadded=row["gflops_unpadded"] / peak,
                   peak_rss_gib=peak_rss_gib())
        rows.append(record("train", edge_heads=args.edge_heads, **row))
    print_table(rows, ["scene", "windows", "mean_n", "programs", "compile_s", "epoch_s",
                       "windows_per_s", "release_epoch_s", "speedup_vs_release",
                       "gflop_unpadded", "gflop_executed", "fraction_of_peak_unpadded",
                       "fraction_of_peak_executed", "compiles_in_epoch", "peak_rss_gib"])


if __name__ == "__main__":
    main()
