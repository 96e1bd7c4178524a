"""Training steps under different memory allocators (glibc, tcmalloc, jemalloc via LD_PRELOAD).

    python benchmarks/bench_allocator.py --scene crowd --steps 30 --repeats 2

XLA's CPU runtime allocates large buffers on every call. glibc's malloc serves them with
fresh mmaps and unmaps them when freed, so every step faults their pages in again (kernel
time: page faults, clearing pages). tcmalloc keeps freed memory for reuse; jemalloc, with
its default settings, hands it back to the kernel after a while.

Each measurement is a child process with the allocator preloaded: it loads (or compiles)
every program its steps need, then times the same first `--steps` optimiser steps of epoch 1
and reports their wall time, user and system CPU time, minor page faults and compilations
(none expected). The allocators take turns, `--repeats` times in a rotated order. An
allocator changes no numerics: the children's final losses must agree bit for bit, and the
table says whether they did.
"""

from __future__ import annotations

import argparse
import ctypes.util
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import jax

from bench_train import program
from common import print_table, record
from gst_jax import data
from gst_jax.cli import use_compilation_cache
from gst_jax.compiles import count_compiles
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.training.state import create_train_state, hparams_for_epoch
from gst_jax.training.step import make_train_step

ALLOCATORS = {"glibc": None, "tcmalloc": "tcmalloc_minimal", "jemalloc": "jemalloc"}


def library(allocator: str) -> str | None:
    """The shared library to preload for `allocator` (None: glibc's own malloc)."""
    name = ALLOCATORS[allocator]
    if name is None:
        return None
    # tcmalloc_minimal (no heap profiler) where it is installed, else the full tcmalloc
    found = ctypes.util.find_library(name) or ctypes.util.find_library(name.split("_")[0])
    if found is None:
        raise SystemExit(f"error: {allocator} not found (Debian: apt-get install "
                         "libtcmalloc-minimal4 libjemalloc2)")
    return found


def time_steps(scene: str, protocol: str, edge_heads: int, seed: int, num_steps: int) -> dict:
    """In this process: compile (or load) the programs of the first steps, then time them."""
    use_compilation_cache()
    config = ModelConfig(num_edge_heads=edge_heads)
    train_config = TrainConfig(seed=seed)
    window_set = data.load_split(DataConfig(scene=scene, protocol=protocol), "train")
    steps = list(data.training_batches(window_set, batch_size=train_config.batch_size,
                                       seed=seed, epoch=1))[:num_steps]
    train_step = make_train_step(config)
    state = create_train_state(config, jax.random.key(seed))
    hparams = hparams_for_epoch(config, train_config, 1)

    shapes = {program(b): b for step in steps for b in step.micro_batches}
    for batch in shapes.values():       # every program once: compiled or read from the cache
        state, metrics = train_step(state, jax.random.key(0), data.PackedStep((batch,), 1),
                                    hparams)
    float(metrics["loss"])

    with count_compiles() as compiles:
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        for index, step in enumerate(steps):
            state, metrics = train_step(state, jax.random.fold_in(jax.random.key(1), index),
                                        step, hparams)
            loss = float(metrics["loss"])            # as the training loop does, every step
        wall_s = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_SELF)
    maps = Path("/proc/self/maps").read_text()
    return {"wall_s": wall_s, "s_per_step": wall_s / len(steps),
            "user_s": after.ru_utime - before.ru_utime,
            "system_s": after.ru_stime - before.ru_stime,
            "minor_faults": after.ru_minflt - before.ru_minflt,
            "compiles_timed": compiles.count,
            "loaded": sorted({name for name in ("tcmalloc", "jemalloc") if name in maps}),
            "final_loss_hex": loss.hex()}


def measure(allocator: str, args: argparse.Namespace) -> dict:
    """One child process with `allocator` preloaded; its measurement."""
    env = dict(os.environ)
    env.pop("LD_PRELOAD", None)
    preload = library(allocator)
    if preload:
        env["LD_PRELOAD"] = preload
    command = [sys.executable, __file__, "--child", "--scene", args.scene, "--protocol",
               args.protocol, "--edge-heads", str(args.edge_heads), "--seed", str(args.seed),
               "--steps", str(args.steps)]
    output = subprocess.run(command, env=env, check=True, stdout=subprocess.PIPE,
                            text=True).stdout
    result = json.loads(output.strip().splitlines()[-1])
    expected = [] if preload is None else [allocator]
    if result["loaded"] != expected:
        raise SystemExit(f"error: {allocator}: the child loaded {result['loaded']}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="crowd", help="training scene (default: crowd)")
    parser.add_argument("--protocol", default="paper", help="split protocol (default: paper)")
    parser.add_argument("--edge-heads", type=int, default=1, help="n (default: 1)")
    parser.add_argument("--seed", type=int, default=1000, help="seed (default: 1000)")
    parser.add_argument("--steps", type=int, default=30,
                        help="optimiser steps timed, the first of epoch 1 (default: 30)")
    parser.add_argument("--repeats", type=int, default=2,
                        help="turns of every allocator (default: 2)")
    parser.add_argument("--allocators", nargs="+", default=list(ALLOCATORS), choices=ALLOCATORS)
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(time_steps(args.scene, args.protocol, args.edge_heads, args.seed,
                                    args.steps)))
        return

    runs: dict[str, list[dict]] = {name: [] for name in args.allocators}
    for turn in range(args.repeats):
        order = args.allocators[turn % len(args.allocators):] + \
            args.allocators[:turn % len(args.allocators)]
        for allocator in order:
            runs[allocator].append(measure(allocator, args))
            print(f"turn {turn + 1}: {allocator} {runs[allocator][-1]['wall_s']:.1f} s",
                  file=sys.stderr)
    losses = {run["final_loss_hex"] for results in runs.values() for run in results}
    baseline = min(r["wall_s"] for r in runs[args.allocators[0]])
    rows = []
    for allocator, results in runs.items():
        best = min(results, key=lambda r: r["wall_s"])
        rows.append(record("allocator", scene=args.scene, protocol=args.protocol,
                           edge_heads=args.edge_heads, steps=args.steps, allocator=allocator,
                           wall_s_each=[round(r["wall_s"], 1) for r in results],
                           best_s_per_step=best["s_per_step"],
                           vs_baseline=best["wall_s"] / baseline,
                           system_s=best["system_s"], user_s=best["user_s"],
                           minor_faults=best["minor_faults"],
                           compiles_timed=sum(r["compiles_timed"] for r in results),
                           same_losses=len(losses) == 1))
    print_table(rows, ["allocator", "wall_s_each", "best_s_per_step", "vs_baseline", "user_s",
                       "system_s", "minor_faults", "compiles_timed", "same_losses"])


if __name__ == "__main__":
    main()
