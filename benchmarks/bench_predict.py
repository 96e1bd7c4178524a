"""Prediction latency and throughput of the jitted `predict`, K = 1 and K = 20.

    python benchmarks/bench_predict.py [--scenes eth hotel univ zara1 zara2] [--sizes 8 16 32 64]

Synthetic scenes of N pedestrians (one window, latency) and the real test sets of each scene
(all windows, batched under the evaluation edge budget: throughput).
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from bench_peak import measure_peak_gflops
from common import flops_of, peak_rss_gib, print_table, record
from gst_jax import data, init_params, make_batch
from gst_jax.config import ETH_UCY_SCENES, DataConfig, ModelConfig
from gst_jax.predict import make_predict

# The authors' release on this project's 2-core CPU (issue 5): one sample of one test window.
RELEASE_MS_PER_WINDOW_SAMPLE = {"zara1": 22.0, "eth": 44.0, "univ": 155.0}


def timed(function, *args, repeats: int) -> float:
    """Best-of-repeats seconds of a call, after one warm-up (compilation) call."""
    jax.block_until_ready(function(*args))
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(function(*args))
        best = min(best, time.perf_counter() - start)
    return best


def synthetic_observations(num_pedestrians: int) -> np.ndarray:
    rng = np.random.default_rng(num_pedestrians)
    xy = np.cumsum(rng.normal(0.3, 0.1, (1, 8, num_pedestrians, 2)), axis=1)
    return xy + rng.uniform(-5, 5, (1, 1, num_pedestrians, 2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="*", default=list(ETH_UCY_SCENES))
    parser.add_argument("--sizes", nargs="*", type=int, default=[8, 16, 32, 64])
    parser.add_argument("--samples", nargs="*", type=int, default=[1, 20])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    config = ModelConfig()
    params = init_params(config, jax.random.key(0))
    key = jax.random.key(1)
    peak = measure_peak_gflops()
    rows = []
    for k in args.samples:
        predict = make_predict(config, num_samples=k, with_graph=False)
        for n in args.sizes:
            batch = make_batch(synthetic_observations(n))
            seconds = timed(predict, params, key, batch, repeats=args.repeats)
            flops = flops_of(predict.lower(params, key, batch).compile())
            rows.append(record("predict", workload=f"N={n}", samples=k, windows=1,
                               ms_per_window=1e3 * seconds,
                               ms_per_window_sample=1e3 * seconds / k,
                               fraction_of_peak=flops / seconds / 1e9 / peak))
        for scene in args.scenes:
            window_set = data.load_split(DataConfig(scene=scene), "test")
            batches = list(data.evaluation_batches(window_set))
            for batch in batches:                       # compile every bucket first
                jax.block_until_ready(predict(params, key, batch))
            start = time.perf_counter()
            for batch in batches:
                jax.block_until_ready(predict(params, key, batch))
            seconds = time.perf_counter() - start
            release = RELEASE_MS_PER_WINDOW_SAMPLE.get(scene)
            rows.append(record("predict", workload=f"{scene} test", samples=k,
                               windows=len(window_set), windows_per_s=len(window_set) / seconds,
                               ms_per_window=1e3 * seconds / len(window_set),
                               ms_per_window_sample=1e3 * seconds / len(window_set) / k,
                               release_ms_per_window_sample=release))
    print(f"peak (matmul): {peak:.0f} GFLOP/s; peak RSS {peak_rss_gib():.2f} GiB")
    print_table(rows, ["workload", "samples", "windows", "ms_per_window", "ms_per_window_sample",
                       "windows_per_s", "release_ms_per_window_sample", "fraction_of_peak"])


if __name__ == "__main__":
    main()
