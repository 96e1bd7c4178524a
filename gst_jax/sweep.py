"""Ablation sweeps as one vmapped program: sparsity n x detection x seeds (paper Figs. 4-6).

    python -m gst_jax.sweep --scene zara1 --edge-heads 0,1,2,4,8,16 --seeds 3 \
        --fully-detected-only both

Every member (n, fully-detected-only, seed) shares one parameter layout (head slots sized for
the largest n) and one compiled `jax.jit(jax.vmap(train_step))`: n, the ghost switch and the
"F" switch are per-member traced values, the data batch is shared. Member k's keys are those of
a single run with its seed, so it trains exactly as that run would on the sweep's data order
(the order of the first seed). A member whose step is not finite keeps its parameters for
that step and the count is reported; the others go on.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import resource
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax import data, evaluate, train
from gst_jax.checkpoints import Checkpointer
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.model import Controls
from gst_jax.predict import make_predict
from gst_jax.train import (HParams, TrainState, create_train_state, hparams_for_epoch,
                           make_train_step)

DETECTION = {"partial": (False,), "full": (True,), "both": (False, True)}


@dataclasses.dataclass(frozen=True)
class Member:
    """One configuration of a sweep: n (0 = full connection), detection, seed."""

    edge_heads: int
    fully_detected_only: bool
    seed: int

    @property
    def detection(self) -> str:
        return "full" if self.fully_detected_only else "partial"

    @property
    def name(self) -> str:
        return f"n{self.edge_heads}-{self.detection}-seed{self.seed}"


def plan_members(edge_heads: Sequence[int], detection: str, seeds: Sequence[int]) -> list[Member]:
    """Every (n, detection, seed) combination, in a fixed order."""
    return [Member(n, fd, seed) for n in edge_heads for fd in DETECTION[detection]
            for seed in seeds]


def sweep_model_config(base: ModelConfig, members: Sequence[Member]) -> ModelConfig:
    """The shared layout: head slots G = lcm of the sparse n, so every member's n divides G."""
    slots = math.lcm(*[max(m.edge_heads, 1) for m in members])
    return dataclasses.replace(base, max_edge_heads=slots, num_edge_heads=members[0].edge_heads)


def member_config(config: ModelConfig, member: Member) -> ModelConfig:
    """The single-run config of a member: its n, the sweep's head slots."""
    return dataclasses.replace(config, num_edge_heads=member.edge_heads)


def stack(trees: Sequence[Any]) -> Any:
    """Stack pytrees of equal structure along a new leading member axis."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def unstack(tree: Any, index: int) -> Any:
    return jax.tree.map(lambda leaf: leaf[index], tree)


def initial_states(config: ModelConfig, members: Sequence[Member]) -> TrainState:
    """Stacked fresh states, member k initialised as a single run of its config and seed."""
    return stack([create_train_state(member_config(config, m),
                                      jax.random.fold_in(jax.random.key(m.seed), 0))
                  for m in members])


def member_hparams(config: ModelConfig, train_config: TrainConfig, members: Sequence[Member],
                   epoch: int) -> HParams:
    """Stacked per-member hyperparameters of a 1-based epoch."""
    return stack([hparams_for_epoch(member_config(config, m), train_config, epoch,
                                    fully_detected_only=m.fully_detected_only)
                  for m in members])


def member_step_keys(members: Sequence[Member], epoch: int, step: int) -> jax.Array:
    """(M,) keys: member k's key for (epoch, step), as `train.fit` derives it from its seed."""
    return jnp.stack([jax.random.fold_in(jax.random.fold_in(jax.random.key(m.seed), epoch), step)
                      for m in members])


def make_sweep_step(config: ModelConfig, *, rotate: bool = True):
    """`jit(vmap(train_step))` over (state, key, hparams) with the batch shared."""
    return jax.jit(jax.vmap(make_train_step(config, rotate=rotate), in_axes=(0, 0, None, 0)),
                   donate_argnums=0)


def load_member(workdir: str | Path, name: str, epoch: int | None = None) -> evaluate.Run:
    """One member of a sweep's stacked checkpoint as a single run (e.g. to simulate it).

    name: a member name such as 'n4-partial-seed1000'. The run's config has the member's n
    and detection switch, and the sweep's head slots.
    """
    workdir = Path(workdir)
    checkpointer = Checkpointer(workdir)
    if checkpointer.latest_epoch is None:
        raise SystemExit(f"error: no checkpoint in {workdir} (expected {workdir}/checkpoints/<epoch>)")
    config = checkpointer.read_config(epoch)
    if "members" not in config:
        raise SystemExit(f"error: {workdir} holds a single run, not a sweep")
    members = [Member(**m) for m in config["members"]]
    names = [m.name for m in members]
    if name not in names:
        raise SystemExit(f"error: {workdir} has no member {name!r}; it has {', '.join(names)}")
    model_config = ModelConfig(**config["model"])
    state, _, epoch = checkpointer.restore(initial_states(model_config, members), epoch)
    checkpointer.close()
    member = members[names.index(name)]
    train_config = TrainConfig(**{**config["train"], "seed": member.seed,
                                  "fully_detected_only": member.fully_detected_only})
    return evaluate.Run(workdir=workdir, model_config=member_config(model_config, member),
                        data_config=DataConfig(**config["data"]), train_config=train_config,
                        params=unstack(state.params, names.index(name)), epoch=epoch)


def fit_sweep(config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
              members: Sequence[Member], workdir: str | Path, *, eval_samples: int = 20,
              max_eval_windows: int = 0, log=sys.stderr) -> dict:
    """Train (or resume) every member in `workdir`, evaluate each on the test split, and write
    results.{json,csv,md} and figures. Returns the results dict."""
    workdir = Path(workdir)
    run_config = {**train.run_config(config, data_config, train_config),
                  "members": [dataclasses.asdict(m) for m in members]}
    train.prepare_workdir(workdir, run_config)
    train_set = train.load_train_set(data_config, train_config)
    state = initial_states(config, members)
    checkpointer = Checkpointer(workdir)
    start_epoch = 1
    if checkpointer.latest_epoch is not None:
        state, _, last_epoch = checkpointer.restore(state)
        start_epoch = last_epoch + 1
        print(f"resuming {workdir} after epoch {last_epoch}", file=log)

    sweep_step = make_sweep_step(config, rotate=train_config.rotate)
    metrics_path = workdir / "metrics.jsonl"
    start = time.perf_counter()
    for epoch in range(start_epoch, train_config.epochs + 1):
        hparams = member_hparams(config, train_config, members, epoch)
        epoch_start = time.perf_counter()
        loss_sum, non_finite, scenes = np.zeros(len(members)), np.zeros(len(members), int), 0
        batches = data.training_batches(train_set, batch_size=train_config.batch_size,
                                        seed=train_config.seed, epoch=epoch)
        for step, batch in enumerate(batches):
            state, step_metrics = sweep_step(state, member_step_keys(members, epoch, step),
                                             batch, hparams)
            real = float(np.sum(batch.scene_mask))
            loss = np.asarray(step_metrics["loss"])
            loss_sum += np.where(np.isfinite(loss), loss, 0.0) * real
            non_finite += ~np.asarray(step_metrics["finite"])
            scenes += real
        record = {"epoch": epoch, "epoch_time_s": time.perf_counter() - epoch_start,
                  "loss": {m.name: float(v) for m, v in zip(members, loss_sum / max(scenes, 1))},
                  "non_finite_steps": {m.name: int(v) for m, v in zip(members, non_finite) if v}}
        if epoch % train_config.checkpoint_every == 0 or epoch == train_config.epochs:
            checkpointer.save(epoch, state, run_config)
        with metrics_path.open("a") as f:
            f.write(json.dumps(record) + "\n")
        losses = loss_sum / max(scenes, 1)
        print(f"epoch {epoch}/{train_config.epochs} {record['epoch_time_s']:.1f} s, "
              f"{len(members)} members, loss min {losses.min():.4g} max {losses.max():.4g}"
              + (f", non-finite steps {record['non_finite_steps']}" if non_finite.any() else ""),
              file=log)
    checkpointer.close()
    train_time = time.perf_counter() - start

    test_set = data.load_split(data_config, "test")
    if max_eval_windows:
        test_set = test_set.subset(range(min(max_eval_windows, len(test_set))))
    evaluations = evaluate_members(state.params, config, test_set, members,
                                   num_samples=eval_samples, log=log)
    results = summarize(evaluations, members, data_config, train_config, eval_samples, test_set)
    results.update(train_time_s=train_time, train_windows=len(train_set),
                   peak_rss_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20)
    write_results(results, workdir)
    return results


def evaluate_members(stacked_params, config: ModelConfig, test_set, members: Sequence[Member],
                     *, num_samples: int, log=sys.stderr) -> list[dict]:
    """Evaluate every member on `test_set` with one compiled `predict` per bucket."""
    predict = make_predict(config, num_samples=num_samples, with_graph=False)
    results = []
    for index, member in enumerate(members):
        controls = Controls.make(0.03, member.edge_heads, config.ghost)
        result = evaluate.evaluate_params(
            unstack(stacked_params, index), config, test_set, jax.random.key(0),
            num_samples=num_samples, with_kde=False, predict=predict, controls=controls,
            fully_detected_only=member.fully_detected_only)
        print(f"{member.name}: AOE {result['aoe']:.3f} FOE {result['foe']:.3f}", file=log)
        results.append(result)
    return results


def partial_detection_density(window_set) -> float:
    """Mean number of partially detected pedestrians per window (the crowd density of Fig. 6)."""
    counts = [w.num_pedestrians - int(np.sum(w.fully_detected())) for w in window_set.windows]
    return float(np.mean(counts)) if counts else 0.0


def _improvement(reference: float, value: float) -> float:
    """Relative improvement in percent of `value` over `reference` (lower is better)."""
    return 100.0 * (reference - value) / reference if reference else float("nan")


def summarize(evaluations: list[dict], members: Sequence[Member], data_config: DataConfig,
              train_config: TrainConfig, num_samples: int, test_set) -> dict:
    """Per (n, detection) cell: AOE/FOE mean and std over seeds; best n; improvements."""
    cells: dict[tuple[int, str], list[dict]] = {}
    for member, result in zip(members, evaluations):
        cells.setdefault((member.edge_heads, member.detection), []).append(result)
    table = []
    for (n, detection), results in sorted(cells.items()):
        aoe = np.array([r["aoe"] for r in results])
        foe = np.array([r["foe"] for r in results])
        table.append({"edge_heads": n, "detection": detection, "seeds": len(results),
                      "aoe": float(aoe.mean()), "aoe_std": float(aoe.std()),
                      "foe": float(foe.mean()), "foe_std": float(foe.std()),
                      "cv_aoe": results[0]["cv_aoe"], "cv_foe": results[0]["cv_foe"]})
    by_cell = {(row["edge_heads"], row["detection"]): row for row in table}
    summary: dict[str, Any] = {}
    for detection in ("partial", "full"):
        sparse = [row for row in table if row["detection"] == detection and row["edge_heads"] > 0]
        full = by_cell.get((0, detection))
        if sparse:
            best = min(sparse, key=lambda row: row["aoe"])      # best n by AOE
            summary[f"best_n_{detection}"] = best["edge_heads"]
            if full:
                summary[f"sparse_vs_full_connection_{detection}"] = {
                    "aoe_pct": _improvement(full["aoe"], best["aoe"]),
                    "foe_pct": _improvement(full["foe"], best["foe"])}
    summary["partial_vs_fully_detected"] = {
        str(n): {"aoe_pct": _improvement(by_cell[(n, "full")]["aoe"], row["aoe"]),
                 "foe_pct": _improvement(by_cell[(n, "full")]["foe"], row["foe"])}
        for (n, detection), row in by_cell.items()
        if detection == "partial" and (n, "full") in by_cell}
    return {
        "scene": data_config.scene,
        "protocol": (f"{data_config.scene}, protocol {data_config.protocol}, test split "
                     f"({len(test_set)} windows), "
                     f"{num_samples} samples (hard, tau 0.03), {train_config.epochs} epochs, "
                     f"seeds {sorted({m.seed for m in members})}"),
        "density": partial_detection_density(test_set),
        "table": table, "members": [{**dataclasses.asdict(m), **r}
                                    for m, r in zip(members, evaluations)],
        **summary,
    }


def format_markdown(results: dict) -> str:
    lines = [f"# Sweep: {results['scene']}", "", f"Protocol: {results['protocol']}.", "",
             "| n | detection | seeds | AOE (m) | FOE (m) |", "|---|---|---|---|---|"]
    for row in results["table"]:
        n = "F (full connection)" if row["edge_heads"] == 0 else str(row["edge_heads"])
        lines.append(f"| {n} | {row['detection']} | {row['seeds']} | "
                     f"{row['aoe']:.3f} ± {row['aoe_std']:.3f} | "
                     f"{row['foe']:.3f} ± {row['foe_std']:.3f} |")
    cv = results["table"][0]
    lines += ["", f"Constant velocity on the same pedestrians: AOE {cv['cv_aoe']:.3f}, "
              f"FOE {cv['cv_foe']:.3f}.",
              f"Partially detected pedestrians per test window: {results['density']:.2f}."]
    for detection in ("partial", "full"):
        if f"best_n_{detection}" in results:
            line = f"Best n ({detection} detection, by AOE): {results[f'best_n_{detection}']}"
            gain = results.get(f"sparse_vs_full_connection_{detection}")
            if gain:
                line += (f"; improvement over full connection: AOE {gain['aoe_pct']:+.1f} %, "
                         f"FOE {gain['foe_pct']:+.1f} %")
            lines.append(line + ".")
    for n, gain in results["partial_vs_fully_detected"].items():
        lines.append(f"n = {n}: partial over fully detected: AOE {gain['aoe_pct']:+.1f} %, "
                     f"FOE {gain['foe_pct']:+.1f} %.")
    return "\n".join(lines) + "\n"


def write_results(results: dict, out_dir: Path) -> None:
    """results.json, results.csv (one row per cell), results.md and figures under out_dir."""
    from gst_jax import figures

    (out_dir / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    with (out_dir / "results.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(results["table"][0]))
        writer.writeheader()
        writer.writerows(results["table"])
    (out_dir / "results.md").write_text(format_markdown(results))
    figures.errors_against_n(results, out_dir / "aoe_foe_vs_n.png")


def parse_edge_heads(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise SystemExit(f"error: --edge-heads expects comma-separated integers, got {text!r}")
    bad = [v for v in values if v not in (0, 1, 2, 4, 8, 16)]
    if bad or not values:
        raise SystemExit(f"error: --edge-heads values must be among 0,1,2,4,8,16, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> None:
    import argparse

    from gst_jax import cli

    parser = argparse.ArgumentParser(prog="python -m gst_jax.sweep",
                                     description=__doc__.split("\n\n")[0])
    cli.add_data_flags(parser)
    parser.add_argument("--edge-heads", default="0,1,2,4,8,16",
                        help="comma-separated n to sweep, 0 = full connection "
                             "(default: 0,1,2,4,8,16)")
    parser.add_argument("--seeds", type=int, default=1,
                        help="seeds per configuration: seed, seed+1, ... (default: 1)")
    parser.add_argument("--fully-detected-only", default="partial", choices=tuple(DETECTION),
                        help="partial: observe everyone (paper default); full: only fully "
                             "detected pedestrians (the paper's 'F'); both (default: partial)")
    parser.add_argument("--no-ghost", action="store_true", help="disable the ghost agent")
    parser.add_argument("--output", default="deterministic", choices=("deterministic", "gaussian"),
                        help="GST (D) or GST (P) (default: deterministic)")
    parser.add_argument("--epochs", type=int, default=TrainConfig.epochs,
                        help=f"epochs (default: {TrainConfig.epochs})")
    parser.add_argument("--batch-size", type=int, default=TrainConfig.batch_size,
                        help=f"scenes per optimiser step (default: {TrainConfig.batch_size})")
    parser.add_argument("--seed", type=int, default=TrainConfig.seed,
                        help=f"first seed; also fixes the shared data order "
                             f"(default: {TrainConfig.seed})")
    parser.add_argument("--eval-samples", type=int, default=20,
                        help="K samples (runs) per member in the evaluation (default: 20)")
    parser.add_argument("--checkpoint-every", type=int, default=TrainConfig.checkpoint_every,
                        help=f"epochs between checkpoints (default: {TrainConfig.checkpoint_every})")
    parser.add_argument("--max-train-windows", type=int, default=0,
                        help="train on the first k windows only (smoke tests; default: all)")
    parser.add_argument("--max-eval-windows", type=int, default=0,
                        help="evaluate on the first k test windows only (smoke tests; "
                             "default: all)")
    cli.add_output_flags(parser, workdir_help="where checkpoints, metrics.jsonl, results and "
                         "figures go; rerunning resumes (default: runs/sweep-<scene>-e<epochs>)")
    args = parser.parse_args(argv)

    members = plan_members(parse_edge_heads(args.edge_heads), args.fully_detected_only,
                           [args.seed + i for i in range(args.seeds)])
    config = sweep_model_config(ModelConfig(ghost=not args.no_ghost, output=args.output), members)
    data_config = cli.data_config(args)
    train_config = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, seed=args.seed,
                               checkpoint_every=args.checkpoint_every,
                               max_train_windows=args.max_train_windows)
    workdir = Path(args.workdir or Path("runs") / f"sweep-{data_config.scene}-e{args.epochs}")
    print(f"work directory: {workdir}; {len(members)} members, head slots "
          f"{config.head_slots}", file=sys.stderr)
    results = fit_sweep(config, data_config, train_config, members, workdir,
                        eval_samples=args.eval_samples, max_eval_windows=args.max_eval_windows)
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(format_markdown(results))
        print(f"written: {workdir}/results.json, .csv, .md, aoe_foe_vs_n.png", file=sys.stderr)


if __name__ == "__main__":
    main()
