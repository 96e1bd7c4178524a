"""Ablation sweeps as one program: sparsity n x detection x seeds (paper Figs. 4-6).

Every member (n, fully-detected-only, seed) shares one parameter layout (head slots sized for
the largest n) and one training step over the members (`make_train_step(..., members=True)`:
looped inside the program on a CPU, vmapped elsewhere): n, the ghost switch and the "F"
switch are per-member traced values, the packed step is shared. Member k's keys are those of
a single run with its seed, so it trains exactly as that run would on the sweep's data order
(the order of the first seed). A member whose step is not finite keeps its parameters for
that step and the count is reported; the others go on.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import resource
import time
from pathlib import Path
from typing import Any, Sequence

import jax
import numpy as np

from gst_jax import data, figures
from gst_jax.config import EVAL_TAU, DataConfig, Member, ModelConfig, TrainConfig
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_params
from gst_jax.io.workdir import WorkDir, run_config
from gst_jax.model import Controls
from gst_jax.parallel import Devices
from gst_jax.predict import make_predict
from gst_jax.progress import Progress
from gst_jax.training.loop import Training, load_train_set, train_epochs
from gst_jax.training.members import member_config, stack, unstack
from gst_jax.training.state import (
    HParams,
    TrainState,
    create_train_state,
    hparams_for_epoch,
    parameter_key,
)
from gst_jax.training.step import make_train_step


def initial_states(config: ModelConfig, members: Sequence[Member]) -> TrainState:
    """Stacked fresh states, member k initialised as a single run of its config and seed."""
    return stack([create_train_state(member_config(config, m), parameter_key(m.seed))
                  for m in members])


def member_hparams(config: ModelConfig, train_config: TrainConfig, members: Sequence[Member],
                   epoch: int) -> HParams:
    """Stacked per-member hyperparameters of a 1-based epoch."""
    return stack([hparams_for_epoch(member_config(config, m), train_config, epoch,
                                    fully_detected_only=m.fully_detected_only)
                  for m in members])


def fit_sweep(config: ModelConfig, data_config: DataConfig, train_config: TrainConfig,
              members: Sequence[Member], workdir: str | Path | WorkDir, *,
              eval_samples: int = 20, max_eval_windows: int = 0, progress: Progress | None = None,
              devices: Devices | None = None) -> dict:
    """Train (or resume) every member in `workdir`, evaluate each on the test split, and write
    results.{json,csv,md} and figures. Returns the results dict. devices: the members are
    split over them in training (members / devices per device), the test windows in
    evaluation."""
    if devices is not None and len(members) % devices.count:
        raise RunError(f"{len(members)} members do not split over {devices.count} devices; "
                       "give --devices a divisor of the member count")
    workdir = workdir if isinstance(workdir, WorkDir) else WorkDir(workdir)
    progress = progress or Progress()
    train_set = load_train_set(data_config, train_config, config.grid)
    sweep_config = run_config(config, data_config, train_config, members)
    training = Training(
        init_state=lambda: initial_states(config, members),
        train_step=make_train_step(config, rotate=train_config.rotate, members=True,
                                   devices=devices),
        hparams=lambda epoch: member_hparams(config, train_config, members, epoch),
        seeds=tuple(m.seed for m in members), member_names=tuple(m.name for m in members))
    start = time.perf_counter()
    with workdir.lock():
        workdir.prepare(sweep_config)
        state, _ = train_epochs(training, workdir, sweep_config, train_set, train_config,
                                stop_on_non_finite=False, progress=progress)
    # Across resumes, as a single run's training_time_s (this process's time alone was 1.47
    # s of 63 for a sweep resumed at its last epoch).
    train_time = workdir.training_time_s() if workdir.writes else time.perf_counter() - start

    test_set = data.load_split(data_config, "test", config.grid)
    if max_eval_windows:
        test_set = test_set.subset(range(min(max_eval_windows, len(test_set))))
    params = devices.gather(state.params) if devices is not None else state.params
    evaluations = evaluate_members(params, config, test_set, members,
                                   num_samples=eval_samples, progress=progress, devices=devices)
    results = summarize(evaluations, members, data_config, train_config, eval_samples, test_set)
    results.update(train_time_s=train_time, train_windows=len(train_set),
                   peak_rss_gib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20)
    if workdir.writes:
        write_results(results, workdir)
    return results


def evaluate_members(stacked_params, config: ModelConfig, test_set: data.WindowSet,
                     members: Sequence[Member], *, num_samples: int,
                     progress: Progress | None = None,
                     devices: Devices | None = None) -> list[dict]:
    """Evaluate every member on `test_set` with one compiled `predict` per bucket (the
    windows of each batch split over `devices`)."""
    progress = progress or Progress()
    predict = make_predict(config, num_samples=num_samples, with_graph=False)
    results = []
    for index, member in enumerate(members):
        controls = Controls.make(EVAL_TAU, member.edge_heads, config.ghost)
        result = evaluate_params(
            unstack(stacked_params, index), jax.random.key(0), test_set, config,
            num_samples=num_samples, with_kde=False, predict=predict, controls=controls,
            fully_detected_only=member.fully_detected_only, devices=devices)
        progress.line(f"{member.name}: AOE {result['aoe']:.3f} FOE {result['foe']:.3f} "
                      f"({index + 1}/{len(members)} evaluated)")
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
                     f"{num_samples} samples (hard, tau {EVAL_TAU}), {train_config.epochs} epochs, "
                     f"seeds {sorted({m.seed for m in members})}"),
        "density": partial_detection_density(test_set),
        "table": table, "members": [{**dataclasses.asdict(m), **r}
                                    for m, r in zip(members, evaluations)],
        **summary,
    }


def format_markdown(results: dict, heading: str = "# Sweep") -> str:
    lines = [f"{heading}: {results['scene']}", "", f"Protocol: {results['protocol']}.", "",
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
                line += f"; against full connection: {_in_words(gain)}"
            lines.append(line + ".")
    for n, gain in results["partial_vs_fully_detected"].items():
        lines.append(f"n = {n}: partial against fully detected: {_in_words(gain)}.")
    return "\n".join(lines) + "\n"


def _in_words(gain: dict) -> str:
    """'AOE 10.5 % better, FOE 3.1 % worse' from {'aoe_pct': 10.5, 'foe_pct': -3.1}."""
    words = []
    for name in ("aoe", "foe"):
        pct = gain[f"{name}_pct"]
        words.append(f"{name.upper()} {abs(pct):.1f} % {'better' if pct >= 0 else 'worse'}")
    return ", ".join(words)


def write_results(results: dict, workdir: WorkDir) -> None:
    """results.json, results.csv (one row per cell), results.md and aoe_foe_vs_n.png."""
    workdir.results_path("json").write_text(json.dumps(results, indent=2) + "\n")
    with workdir.results_path("csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(results["table"][0]))
        writer.writeheader()
        writer.writerows(results["table"])
    workdir.results_path("md").write_text(format_markdown(results))
    figures.errors_against_n(results, workdir.path / "aoe_foe_vs_n.png")
