"""The machine's measured dense float32 matmul throughput (GFLOP/s), the 'peak' of the tables.

    python benchmarks/bench_peak.py [--size 2048] [--repeats 20]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp

from common import print_table, record


def measure_peak_gflops(size: int = 2048, repeats: int = 20) -> float:
    """Best-of-repeats GFLOP/s of a jitted (size x size) @ (size x size) float32 matmul."""
    a = jax.random.normal(jax.random.key(0), (size, size), jnp.float32)
    matmul = jax.jit(lambda x: x @ x)
    matmul(a).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        matmul(a).block_until_ready()
        best = min(best, time.perf_counter() - start)
    return 2 * size ** 3 / best / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    row = record("peak", size=args.size, gflops=measure_peak_gflops(args.size, args.repeats))
    print_table([row], ["machine", "size", "gflops"])


if __name__ == "__main__":
    main()
