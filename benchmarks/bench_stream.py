"""One stream step for a robot, and for many robots at once: observe a frame, predict every
track, issue DtACI regions (`gst_jax.stream.make_step`).

    python benchmarks/bench_stream.py                         # 50 people; 1 and 16 robots
    python benchmarks/bench_stream.py --people 20 --robots 1 16 --candidates 0 16

CrowdNav++'s predictor (`pretrained:crowdnav_sj`: 5 observed and 5 predicted steps of
0.25 s, full connection, mean mode) tracks `--people` walkers in a stream of capacity
bucket_size(people); pooled DtACI regions at alpha = 0.1. The step is jitted (vmapped over
robots for more than one, each robot its own crowd) and fed frames of a scripted crowd: the
first obs_len + pred_len steps fill the histories and the score buffers, then `--calls` steps
are timed one by one (`block_until_ready`), median reported. `--candidates` k > 0 predicts with
each person's k nearest as the only candidates (`ModelConfig.candidates`).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from common import print_table, record
from gst_jax.conformal import Regions
from gst_jax.data import bucket_size
from gst_jax.runs import load_model
from gst_jax.stream import Frame, StreamModel, init_state, make_step


def walkers(robots: int, people: int, steps: int, step_s: float) -> np.ndarray:
    """(steps, robots, people, 2) positions: straight walks at 0.5-1.5 m/s with a little
    noise, spread over a 12 m square."""
    rng = np.random.default_rng(0)
    start = rng.uniform(-6, 6, (robots, people, 2))
    heading = rng.uniform(0, 2 * np.pi, (robots, people))
    velocity = rng.uniform(0.5, 1.5, (robots, people, 1)) * np.stack(
        [np.cos(heading), np.sin(heading)], -1)
    t = np.arange(steps)[:, None, None, None] * step_s
    return start + velocity * t + rng.normal(0, 0.02, (steps, robots, people, 2))


def time_case(run, robots: int, people: int, candidates: int, calls: int) -> dict:
    config = dataclasses.replace(run.model_config, candidates=candidates)
    regions = Regions("dtaci", 0.1)
    step = make_step(StreamModel(config, convention="gst"), regions)
    capacity = bucket_size(people)
    state = init_state(capacity, config.obs_len, regions, config.pred_len)
    if robots > 1:
        step = jax.vmap(step, in_axes=(None, 0, 0, 0))
        state = jax.tree.map(lambda leaf: jnp.broadcast_to(leaf, (robots,) + leaf.shape), state)
    step = jax.jit(step)
    warm = config.obs_len + config.pred_len
    xy = walkers(robots, people, warm + calls, config.step_s).astype(np.float32)
    ids = np.broadcast_to(np.pad(np.arange(people), (0, capacity - people),
                                 constant_values=-1), (robots, capacity)).astype(np.int32)
    key = jax.random.key(0)
    seconds, compile_s = [], None
    for t in range(warm + calls):
        positions = np.pad(xy[t], [(0, 0), (0, capacity - people), (0, 0)])
        frame = Frame(ids, positions) if robots > 1 else Frame(ids[0], positions[0])
        keys = jax.random.split(jax.random.fold_in(key, t), robots) if robots > 1 else (
            jax.random.fold_in(key, t))
        start = time.perf_counter()
        state, futures, *_ = step(run.params, state, frame, keys)
        futures.block_until_ready()
        elapsed = time.perf_counter() - start
        if t == 0:
            compile_s = elapsed
        elif t >= warm:
            seconds.append(elapsed)
    return {"median_ms": 1e3 * statistics.median(seconds), "min_ms": 1e3 * min(seconds),
            "compile_s": compile_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="pretrained:crowdnav_sj")
    parser.add_argument("--people", nargs="*", type=int, default=[50])
    parser.add_argument("--robots", nargs="*", type=int, default=[1, 16])
    parser.add_argument("--candidates", nargs="*", type=int, default=[0, 16])
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--note", default="", help="recorded with the rows (e.g. the load)")
    args = parser.parse_args()
    run = load_model(args.model)
    rows = []
    for people in args.people:
        for robots in args.robots:
            for candidates in args.candidates:
                result = time_case(run, robots, people, candidates, args.calls)
                rows.append(record("stream", model=args.model, people=people, robots=robots,
                                   candidates=candidates, calls=args.calls, note=args.note,
                                   **result))
    print_table(rows, ["people", "robots", "candidates", "median_ms", "min_ms", "compile_s"])


if __name__ == "__main__":
    main()
