"""Sweep cost: one vmapped program for all configurations vs training them one after another.

    python benchmarks/bench_sweep.py --scene zara1 --edge-heads 0,1,2,4,8,16 --steps 12

Three ways to take the same optimiser steps for every configuration (wall time, compilation
included, as a user would pay it):
  vmapped     one vmapped training step over the stacked members (gst_jax.training.sweep);
  sequential  the same traced-n program (head slots for the largest n), one member at a time;
  separate    each configuration as its own single run (head slots = max(n, 1)), compiled
              for itself, one after another.
"""

from __future__ import annotations

import argparse
import time

import jax

from common import peak_rss_gib, print_table, record
from gst_jax import cli, data
from gst_jax.config import SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.training import members as sweep_members, state as train_state, sweep
from gst_jax.training import step as train_step


def timed_steps(step, state, batches, keys_for, hparams):
    """(compile_s, run_s) of taking every batch once; compile = first call of each shape."""
    compile_s = run_s = 0.0
    seen = set()
    for index, packed in enumerate(batches):
        start = time.perf_counter()
        state, metrics = step(state, keys_for(index), packed, hparams)
        jax.block_until_ready(metrics["loss"])
        elapsed = time.perf_counter() - start
        shapes = {b.shape for b in packed.micro_batches}
        if shapes <= seen:
            run_s += elapsed
        else:
            seen |= shapes
            compile_s += elapsed
    return compile_s, run_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="zara1", choices=SCENES, help="dataset (default: zara1)")
    parser.add_argument("--edge-heads", default="0,1,2,4,8,16", help="n to sweep")
    parser.add_argument("--seeds", type=int, default=1, help="seeds per configuration")
    parser.add_argument("--steps", type=int, default=12, help="optimiser steps per member")
    parser.add_argument("--seed", type=int, default=1000, help="first seed (default: 1000)")
    args = parser.parse_args()

    members = sweep_members.plan_members(cli.parse_edge_heads(args.edge_heads), "partial",
                                         [args.seed + i for i in range(args.seeds)])
    config = sweep_members.sweep_model_config(ModelConfig(), members)
    train_config = TrainConfig(seed=args.seed)
    window_set = data.load_split(DataConfig(scene=args.scene), "train")
    batches = list(data.training_batches(window_set, batch_size=16, seed=args.seed, epoch=1))
    batches = (batches * (args.steps // len(batches) + 1))[:args.steps]
    key = jax.random.key(0)
    rows = []

    def way(name, run):
        start = time.perf_counter()
        compile_s, run_s = run()
        rows.append(dict(way=name, compile_s=compile_s, run_s=run_s,
                         total_s=time.perf_counter() - start))

    def one_after_another(config_of, step_of):
        """Every member alone: its config, its (possibly shared) jitted step."""
        compile_s = run_s = 0.0
        for member in members:
            alone = config_of(member)
            c, r = timed_steps(step_of(alone), train_state.create_train_state(alone, key), batches,
                               lambda i: jax.random.fold_in(key, i),
                               train_state.hparams_for_epoch(alone, train_config, 1))
            compile_s, run_s = compile_s + c, run_s + r
        return compile_s, run_s

    way("vmapped", lambda: timed_steps(
        train_step.make_train_step(config, members=True), sweep.initial_states(config, members),
        batches,
        lambda i: jax.random.split(jax.random.fold_in(key, i), len(members)),
        sweep.member_hparams(config, train_config, members, 1)))
    shared_step = train_step.make_train_step(config)
    way("sequential", lambda: one_after_another(
        lambda m: sweep_members.member_config(config, m), lambda alone: shared_step))
    way("separate", lambda: one_after_another(                      # head slots max(n, 1)
        lambda m: ModelConfig(num_edge_heads=m.edge_heads),
        lambda alone: train_step.make_train_step(alone)))

    for row in rows:
        row.update(record("sweep", scene=args.scene, members=len(members), steps=args.steps,
                          head_slots=config.head_slots, **row))
        row["vs_vmapped"] = row["total_s"] / rows[0]["total_s"]
    print(f"{len(members)} members x {args.steps} steps on {args.scene}; "
          f"peak RSS {peak_rss_gib():.2f} GiB")
    print_table(rows, ["way", "compile_s", "run_s", "total_s", "vs_vmapped"])


if __name__ == "__main__":
    main()
