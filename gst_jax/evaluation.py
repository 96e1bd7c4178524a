"""Evaluation with the paper's protocol (docs/MODEL.md 4) and the standard metrics.

Metrics count fully detected pedestrians only. K = 20 hard-sampled predictions of every
window are the paper's "20 runs of the whole test set": run k is sample k of every window,
so AOE/FOE are reported as the mean over runs with the spread (std) across runs. Beside them:
best-of-K minADE/minFDE, KDE NLL (Trajectron++ rule), the collision rate of predictions and
of the ground truth, and a constant-velocity baseline on exactly the same pedestrians.
"""

from __future__ import annotations

import time
from typing import Any

import jax
import numpy as np

from gst_jax import data, graph, metrics
from gst_jax.config import EVAL_TAU, DataConfig, ModelConfig
from gst_jax.model import Controls
from gst_jax.predict import make_predict
from gst_jax.progress import Progress

# Scenes whose batches of (padded) pedestrians fit this many padded edges share one program.
DEFAULT_EDGE_BUDGET = 16 * 32 * 32


def evaluate_params(params, key: jax.Array, window_set: data.WindowSet, config: ModelConfig, *,
                    num_samples: int = 20, edge_budget: int = DEFAULT_EDGE_BUDGET,
                    with_kde: bool = True, with_baseline: bool = True,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None, progress: Progress | None = None) -> dict[str, Any]:
    """Evaluate `params` on every window of `window_set`; returns a flat dict of metrics.

    fully_detected_only: the model observes fully detected pedestrians only (a run trained
    with the "F" baseline is tested the same way). controls: traced n / ghost overriding the
    config's (sweeps), at tau = EVAL_TAU. predict: a `make_predict(config, num_samples,
    with_graph=False)` to reuse across calls (one compile per bucket for many members).
    progress: reports the windows evaluated, with an ETA.
    """
    predict = predict or make_predict(config, num_samples=num_samples, with_graph=False)
    # scipy's 2-D KDE needs more samples than dimensions; with K <= 2 there is no KDE NLL.
    with_kde = with_kde and num_samples > 2
    obs_len = config.obs_len
    totals: dict[str, Any] = {}

    def add(name, value):
        totals[name] = totals.get(name, 0.0) + np.asarray(value, dtype=np.float64)

    batches = list(data.evaluation_batches(window_set, edge_budget=edge_budget))
    started, done = time.perf_counter(), 0
    for batch_index, batch in enumerate(batches):
        if fully_detected_only:
            batch = jax.tree.map(np.asarray, graph.drop_partially_detected(batch, True))
        prediction = predict(params, jax.random.fold_in(key, batch_index), batch, controls)
        pred = np.asarray(prediction.positions)                      # (K, B, P, N, 2)
        truth = np.asarray(batch.positions[:, obs_len:])             # (B, P, N, 2)
        eval_mask = metrics.fully_detected_mask(batch.node_mask) * batch.scene_mask[:, None]
        for name, value in metrics.aoe_foe_sums(pred, truth, eval_mask).items():
            add(name, value)
        for name, value in metrics.min_ade_fde_sums(pred, truth, eval_mask).items():
            add(name, value)
        if with_kde:
            for name, value in metrics.kde_nll_sums(pred, truth, eval_mask).items():
                add("kde_" + name, value)
        predicted_mask = np.asarray(prediction.predicted_mask) * batch.scene_mask[:, None]
        collisions, pairs = metrics.collision_sums(pred, predicted_mask)
        add("pred_collisions", np.sum(collisions))
        add("pred_pairs", np.sum(pairs))
        truth_step_mask = batch.position_mask[:, obs_len:] * batch.scene_mask[:, None, None]
        collisions, pairs = metrics.collision_sums(truth, predicted_mask, truth_step_mask)
        add("truth_collisions", np.sum(collisions))
        add("truth_pairs", np.sum(pairs))
        if with_baseline:
            for name, value in _constant_velocity_sums(batch, obs_len, eval_mask).items():
                add("cv_" + name, value)
        done += int(batch.scene_mask.sum())
        if progress is not None:
            progress.count("windows evaluated", done, len(window_set), started)
    return _summarize(totals, num_samples, with_kde, with_baseline)


def constant_velocity_baseline(window_set: data.WindowSet, *, obs_len: int = 8) -> dict[str, Any]:
    """The constant-velocity column of `evaluate_params` without a model: AOE/FOE on the
    fully detected pedestrians of `window_set` (same windows, same pedestrians)."""
    totals: dict[str, Any] = {}
    for batch in data.evaluation_batches(window_set):
        eval_mask = metrics.fully_detected_mask(batch.node_mask) * batch.scene_mask[:, None]
        for name, value in _constant_velocity_sums(batch, obs_len, eval_mask).items():
            totals[name] = totals.get(name, 0.0) + np.asarray(value, dtype=np.float64)
    count = float(totals["count"])
    return {"pedestrians": int(count), "cv_aoe": float(totals["aoe_sum"][0] / max(count, 1.0)),
            "cv_foe": float(totals["foe_sum"][0] / max(count, 1.0))}


def _constant_velocity_sums(batch, obs_len: int, eval_mask: np.ndarray) -> dict:
    truth = np.asarray(batch.positions[:, obs_len:])                 # (B, P, N, 2)
    cv = metrics.constant_velocity(batch.positions[:, :obs_len], batch.node_mask[:, :obs_len],
                                   pred_len=truth.shape[1])
    return metrics.aoe_foe_sums(cv[None], truth, eval_mask)


def _summarize(totals: dict, num_samples: int, with_kde: bool, with_baseline: bool) -> dict:
    count = float(totals["count"])
    runs_aoe = totals["aoe_sum"] / max(count, 1.0)
    runs_foe = totals["foe_sum"] / max(count, 1.0)
    result = {
        "pedestrians": int(count),
        "samples": num_samples,
        "aoe": float(np.mean(runs_aoe)), "aoe_std": float(np.std(runs_aoe)),
        "foe": float(np.mean(runs_foe)), "foe_std": float(np.std(runs_foe)),
        "min_ade": float(totals["min_ade_sum"] / max(count, 1.0)),
        "min_fde": float(totals["min_fde_sum"] / max(count, 1.0)),
        "collision_rate": float(totals["pred_collisions"] / max(totals["pred_pairs"], 1.0)),
        "truth_collision_rate": float(totals["truth_collisions"]
                                      / max(totals["truth_pairs"], 1.0)),
    }
    if with_kde:
        result["kde_nll"] = float(totals["kde_nll_sum"] / max(totals["kde_count"], 1.0))
    if with_baseline:
        result["cv_aoe"] = float(totals["cv_aoe_sum"][0] / max(count, 1.0))
        result["cv_foe"] = float(totals["cv_foe_sum"][0] / max(count, 1.0))
    return result


def protocol_line(data_config: DataConfig, split: str, num_samples: int, epochs: int) -> str:
    return (f"{data_config.scene}, protocol {data_config.protocol}, {split} split, "
            f"{num_samples} samples (hard, tau {EVAL_TAU}), {epochs} epochs")


def format_table(result: dict) -> str:
    """A readable table of one evaluation, the protocol on top."""
    rows = [("GST", f"{result['aoe']:.3f} ± {result['aoe_std']:.3f}",
             f"{result['foe']:.3f} ± {result['foe_std']:.3f}",
             f"{result['min_ade']:.3f}", f"{result['min_fde']:.3f}",
             f"{result['kde_nll']:.2f}" if "kde_nll" in result else "-",
             f"{100 * result['collision_rate']:.2f}%")]
    if "cv_aoe" in result:
        rows.append(("constant velocity", f"{result['cv_aoe']:.3f}", f"{result['cv_foe']:.3f}",
                     "-", "-", "-", "-"))
    rows.append(("ground truth", "-", "-", "-", "-", "-",
                 f"{100 * result['truth_collision_rate']:.2f}%"))
    header = ("model", "AOE (m)", "FOE (m)", "minADE", "minFDE", "KDE NLL", "collisions")
    widths = [max(len(str(r[i])) for r in (header, *rows)) for i in range(len(header))]
    lines = [result["protocol"], f"{result['pedestrians']} fully detected pedestrians", ""]
    for row in (header, *rows):
        lines.append("  ".join(str(c).ljust(w) for c, w in zip(row, widths)))
    return "\n".join(lines)


def format_markdown(result: dict) -> str:
    lines = [f"Protocol: {result['protocol']}; {result['pedestrians']} fully detected pedestrians.",
             "", "| model | AOE (m) | FOE (m) | minADE | minFDE | KDE NLL | collisions |",
             "|---|---|---|---|---|---|---|",
             f"| GST | {result['aoe']:.3f} ± {result['aoe_std']:.3f} | "
             f"{result['foe']:.3f} ± {result['foe_std']:.3f} | {result['min_ade']:.3f} | "
             f"{result['min_fde']:.3f} | "
             + (f"{result['kde_nll']:.2f}" if "kde_nll" in result else "-")
             + f" | {100 * result['collision_rate']:.2f}% |"]
    if "cv_aoe" in result:
        lines.append(f"| constant velocity | {result['cv_aoe']:.3f} | {result['cv_foe']:.3f} "
                     "| - | - | - | - |")
    lines.append(f"| ground truth | - | - | - | - | - | "
                 f"{100 * result['truth_collision_rate']:.2f}% |")
    return "\n".join(lines) + "\n"


def evaluate_run(run, data_config: DataConfig, split: str, *, num_samples: int = 20,
                 seed: int = 0, with_kde: bool = True,
                 progress: Progress | None = None) -> dict[str, Any]:
    """Evaluate a loaded model (`gst_jax.runs.Run`) on one split: the metrics of
    `evaluate_params` plus what was evaluated (scene, split, windows, epoch, protocol line)."""
    window_set = data.load_split(data_config, split)
    if not len(window_set):
        raise data.DataError(f"{data_config.scene}: the {split} split has no window")
    result = evaluate_params(run.params, jax.random.key(seed), window_set, run.model_config,
                             num_samples=num_samples, with_kde=with_kde,
                             fully_detected_only=run.train_config.fully_detected_only,
                             progress=progress)
    result.update(model=run.name, scene=data_config.scene, protocol_name=data_config.protocol,
                  split=split,
                  windows=len(window_set), epoch=run.epoch, output=run.model_config.output,
                  num_edge_heads=run.model_config.num_edge_heads,
                  protocol=protocol_line(data_config, split, num_samples, run.epoch))
    return result
