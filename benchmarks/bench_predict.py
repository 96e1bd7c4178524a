"""Prediction: K samples of every test window, against one sample of the release, same run.

    python benchmarks/bench_predict.py --scenes eth zara1
    python benchmarks/bench_predict.py --scenes eth --release-dir REL --release-python PY

Ours: the jitted `predict` over a scene's whole test set in the evaluation's batches (every
bucket compiled first), K = 1 and K = 20, milliseconds per window; and single synthetic
windows of N pedestrians (a planner's latency). The release (optional, see release.py): its
one-sample inference over the same test windows, timed in the same run.
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from bench_peak import measure_peak_gflops
from common import matmul_flops, peak_rss_gib, print_table, record
from gst_jax import data, init_params, make_batch
from gst_jax.config import SCENES, DataConfig, ModelConfig
from gst_jax.predict import make_predict
from release import time_release


def best_of(function, repeats: int) -> float:
    """Best-of-repeats seconds of a call, after one warm-up (compilation) call."""
    jax.block_until_ready(function())
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function())
        best = min(best, time.perf_counter() - start)
    return best


def synthetic_observations(num_pedestrians: int) -> np.ndarray:
    rng = np.random.default_rng(num_pedestrians)
    xy = np.cumsum(rng.normal(0.3, 0.1, (1, 8, num_pedestrians, 2)), axis=1)
    return xy + rng.uniform(-5, 5, (1, 1, num_pedestrians, 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="*", default=["eth", "zara1"], choices=SCENES)
    parser.add_argument("--sizes", nargs="*", type=int, default=[8, 16, 32, 64])
    parser.add_argument("--samples", nargs="*", type=int, default=[1, 20])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--release-dir", default=None)
    parser.add_argument("--release-python", default=None)
    parser.add_argument("--release-threads", type=int, default=2)
    args = parser.parse_args()

    config = ModelConfig()
    params = init_params(config, jax.random.key(0))
    key = jax.random.key(1)
    peak = measure_peak_gflops()
    release = {scene: time_release(args.release_dir, args.release_python, scene, windows=10 ** 6,
                                   threads=args.release_threads)["test"]
               for scene in (args.scenes if args.release_dir else [])}
    rows = []
    for k in args.samples:
        predict = make_predict(config, num_samples=k, with_graph=False)
        for n in args.sizes:
            batch = make_batch(synthetic_observations(n))
            seconds = best_of(lambda: predict(params, key, batch), args.repeats)
            flops = matmul_flops(lambda p: predict(p, key, batch).positions, params)
            rows.append(record("predict", workload=f"N={n}", samples=k, windows=1,
                               ms_per_window=1e3 * seconds,
                               fraction_of_peak=flops / seconds / 1e9 / peak))
        for scene in args.scenes:
            window_set = data.load_split(DataConfig(scene=scene), "test")
            batches = list(data.evaluation_batches(window_set))

            def whole_test_set():
                return [predict(params, key, b).positions for b in batches]

            seconds = best_of(whole_test_set, args.repeats)
            ours_ms = 1e3 * seconds / len(window_set)
            theirs = release.get(scene)
            rows.append(record(
                "predict", workload=f"{scene} test", samples=k, windows=len(window_set),
                ms_per_window=ours_ms,
                release_one_sample_ms=theirs["ms_per_window"] if theirs else None,
                vs_release_one_sample=ours_ms / theirs["ms_per_window"] if theirs else None))
    print(f"peak (matmul): {peak:.0f} GFLOP/s; peak RSS {peak_rss_gib():.2f} GiB")
    print_table(rows, ["workload", "samples", "windows", "ms_per_window",
                       "release_one_sample_ms", "vs_release_one_sample", "fraction_of_peak"])


if __name__ == "__main__":
    main()
