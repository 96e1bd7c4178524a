"""Sweep cost per member-epoch: the layouts of a sweep's members on this machine.

    python benchmarks/bench_sweep.py --scene eth --edge-heads 0,1,2,4,8,16 --seeds 3 \\
        --detection both --steps 4

The same optimiser steps (the first `--steps` of epoch 1, the same batches for every member)
taken by every member of the sweep, in each layout: once to compile every shape they meet,
then again, timed:

  all-vmap    every member in one vmapped program, head slots for the largest n (lcm)
  all-map     the same program with the members looped inside it (`lax.map`), not vmapped
  n-vmap      one vmapped program per n (its seeds and detection modes), head slots n
  n-map       one program per n, members looped inside it
  runs        each member alone, as a single run of its own (head slots max(n, 1))

Reports, per layout and n, the seconds per member-step and the projected member-epoch
(`steps per epoch x member-step`), and the compile time of the layout's programs.
"""

from __future__ import annotations

import argparse
import math
import time

import jax

from common import peak_rss_gib, print_table, record
from gst_jax import cli, data
from gst_jax.config import DETECTION, SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.training import (
    members as sweep_members,
    state as train_state,
    step as train_step,
    sweep,
)

LAYOUTS = ("all-vmap", "all-map", "n-vmap", "n-map", "runs")


def timed(step, state, batches, keys_for, hparams) -> tuple[float, float]:
    """(seconds of a first pass over the batches, compiling each shape; seconds per step of
    a second pass over the same batches, nothing left to compile)."""
    seconds = []
    for _ in range(2):
        start = time.perf_counter()
        for index, packed in enumerate(batches):
            state, metrics = step(state, keys_for(index), packed, hparams)
        jax.block_until_ready(metrics["loss"])
        seconds.append(time.perf_counter() - start)
    return seconds[0], seconds[1] / len(batches)


def program(members, train_config, batches, *, member_map: bool) -> tuple[float, float]:
    """One sweep program over `members`: (first step s, s per step after it)."""
    config = sweep_members.sweep_model_config(ModelConfig(), members)
    step = train_step.TrainStep(config, members=True, member_map=member_map)
    key = jax.random.key(0)
    return timed(step, sweep.initial_states(config, members), batches,
                 lambda i: jax.random.split(jax.random.fold_in(key, i), len(members)),
                 sweep.member_hparams(config, train_config, members, 1))


def single_run(member, train_config, batches) -> tuple[float, float]:
    config = ModelConfig(num_edge_heads=member.edge_heads)
    step = train_step.TrainStep(config)
    key = jax.random.key(0)
    return timed(step, train_state.create_train_state(config, key), batches,
                 lambda i: jax.random.fold_in(key, i),
                 train_state.hparams_for_epoch(config, train_config, 1,
                                               fully_detected_only=member.fully_detected_only))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="eth", choices=SCENES, help="dataset (default: eth)")
    parser.add_argument("--edge-heads", default="0,1,2,4,8,16", type=cli.parse_edge_heads,
                        help="n to sweep (default: 0,1,2,4,8,16)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per configuration")
    parser.add_argument("--detection", default="both", choices=tuple(DETECTION))
    parser.add_argument("--steps", type=int, default=4,
                        help="optimiser steps per member and pass (default: 4)")
    parser.add_argument("--layouts", default=",".join(LAYOUTS),
                        help=f"comma-separated, of {', '.join(LAYOUTS)}")
    args = parser.parse_args()

    members = sweep_members.plan_members(args.edge_heads, args.detection,
                                         [1000 + i for i in range(args.seeds)])
    train_config = TrainConfig()
    window_set = data.load_split(DataConfig(scene=args.scene), "train")
    steps_per_epoch = math.ceil(len(window_set) / train_config.batch_size)
    batches = list(data.training_batches(window_set, batch_size=16, seed=1000, epoch=1))
    batches = (batches * (args.steps // len(batches) + 1))[:args.steps]
    by_n = {n: [m for m in members if m.edge_heads == n] for n in args.edge_heads}
    rows = []

    def add(layout, n, count, first, per_step):
        member_step = per_step / count
        rows.append(record(
            "sweep_layouts", scene=args.scene, layout=layout, n=n, members=count,
            compile_s=first - per_step * args.steps, member_step_s=member_step,
            member_epoch_s=member_step * steps_per_epoch, steps=args.steps))

    for layout in args.layouts.split(","):
        if layout.startswith("all-"):
            first, per_step = program(members, train_config, batches,
                                      member_map=layout == "all-map")
            add(layout, "all", len(members), first, per_step)
        elif layout.startswith("n-"):
            for n, group in by_n.items():
                first, per_step = program(group, train_config, batches,
                                          member_map=layout == "n-map")
                add(layout, n, len(group), first, per_step)
        elif layout == "runs":
            for n, group in by_n.items():       # seeds and detection cost alike: one each
                first, per_step = single_run(group[0], train_config, batches)
                add(layout, n, 1, first, per_step)
        else:
            raise SystemExit(f"unknown layout {layout!r}; choose from {', '.join(LAYOUTS)}")
        print_table(rows[-1:], ["layout", "n", "members", "compile_s", "member_step_s",
                                "member_epoch_s"])
    print(f"{args.scene}: {len(window_set)} training windows, {steps_per_epoch} steps an "
          f"epoch; peak RSS {peak_rss_gib():.2f} GiB")
    print_table(rows, ["layout", "n", "members", "compile_s", "member_step_s", "member_epoch_s"])


if __name__ == "__main__":
    main()
