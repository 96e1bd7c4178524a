"""Evaluation with the paper's protocol (docs/MODEL.md 4) and the standard metrics.

Metrics count fully detected pedestrians only. K = 20 hard-sampled predictions of every
window are the paper's "20 runs of the whole test set": run k is sample k of every window,
so AOE/FOE are reported as the mean over runs with the spread (std) across runs. Beside them:
best-of-K minADE/minFDE, KDE NLL (Trajectron++ rule), the collision rate of predictions and
of the ground truth, TrajNet++'s Col-I / Col-II, and a constant-velocity baseline on exactly
the same pedestrians. The same metrics score a TrajNet++ prediction file
(`evaluate_prediction_file`), ours (`write_run_predictions`) or another model's.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable, Iterator

import jax
import numpy as np

from gst_jax import data, graph, metrics
from gst_jax.config import EVAL_TAU, DataConfig, ModelConfig
from gst_jax.model import Controls
from gst_jax.parallel import Devices
from gst_jax.predict import make_predict
from gst_jax.prediction_files import PredictedBatch, read_predictions, write_predictions
from gst_jax.progress import Progress

# Scenes whose batches of (padded) pedestrians fit this many padded edges share one program.
DEFAULT_EDGE_BUDGET = 16 * 32 * 32


def evaluate_params(params, key: jax.Array, window_set: data.WindowSet, config: ModelConfig, *,
                    num_samples: int = 20, edge_budget: int = DEFAULT_EDGE_BUDGET,
                    with_kde: bool = True, with_baseline: bool = True,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None, progress: Progress | None = None,
                    devices: Devices | None = None) -> dict[str, Any]:
    """Evaluate `params` on every window of `window_set`; returns a flat dict of metrics.

    The arguments are those of `predict_windows`; with_kde / with_baseline: also the KDE NLL /
    the constant-velocity baseline.
    """
    predicted = predict_windows(params, key, window_set, config, num_samples=num_samples,
                                edge_budget=edge_budget, fully_detected_only=fully_detected_only,
                                controls=controls, predict=predict, progress=progress,
                                devices=devices)
    return score(predicted, obs_len=config.obs_len, with_kde=with_kde,
                 with_baseline=with_baseline)


def predict_windows(params, key: jax.Array, window_set: data.WindowSet, config: ModelConfig, *,
                    num_samples: int = 20, edge_budget: int = DEFAULT_EDGE_BUDGET,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None, progress: Progress | None = None,
                    devices: Devices | None = None) -> Iterator[PredictedBatch]:
    """K sampled futures of every window, batch by batch (`data.evaluation_batches`).

    Sample k of a window depends on the key, k and the window's index only (`noise`), not
    on its batch: the same key gives the same samples whatever the batching or the devices,
    to an evaluation and to a prediction file alike. fully_detected_only: the model observes
    fully detected pedestrians only (a run trained with the "F" baseline is tested the same
    way). controls: traced n / ghost overriding the config's (sweeps), at tau = EVAL_TAU.
    predict: a `make_predict(config, num_samples, with_graph=False)` to reuse across calls
    (one compile per bucket for many members). progress: reports the windows predicted, with
    an ETA. devices: the scenes of each batch are split over them.
    """
    predict = predict or make_predict(config, num_samples=num_samples, with_graph=False)
    if devices is not None:
        params, key, controls = devices.replicate((params, key, controls))
    started, done = time.perf_counter(), 0
    for batch in data.evaluation_batches(window_set, edge_budget=edge_budget,
                                         batch_multiple=devices.count if devices else 1):
        if fully_detected_only:
            batch = jax.tree.map(np.asarray, graph.drop_partially_detected(batch, True))
        prediction = predict(params, key, devices.split(batch) if devices else batch, controls)
        outputs = (prediction.positions, prediction.predicted_mask)
        positions, predicted_mask = (devices.gather(outputs) if devices
                                     else jax.tree.map(np.asarray, outputs))
        yield PredictedBatch(batch, positions, predicted_mask * batch.scene_mask[:, None])
        done += int(batch.scene_mask.sum())
        if progress is not None:
            progress.count("windows predicted", done, len(window_set), started)


def score(predicted: Iterable[PredictedBatch], *, obs_len: int, with_kde: bool = True,
          with_baseline: bool = True) -> dict[str, Any]:
    """The metrics of sampled futures against the windows' own: AOE/FOE per run, best-of-K,
    KDE NLL, collisions (0.1 m, and TrajNet++'s Col-I / Col-II), constant velocity."""
    totals: dict[str, Any] = {}

    def add(name, value):
        totals[name] = totals.get(name, 0.0) + np.asarray(value, dtype=np.float64)

    num_samples = 0
    for batch, pred, predicted_mask in predicted:                    # pred (K, B, P, N, 2)
        num_samples = pred.shape[0]
        # scipy's 2-D KDE needs more samples than dimensions; with K <= 2 there is no KDE NLL.
        with_kde = with_kde and num_samples > 2
        truth = np.asarray(batch.positions[:, obs_len:])             # (B, P, N, 2)
        truth_step_mask = batch.position_mask[:, obs_len:] * batch.scene_mask[:, None, None]
        eval_mask = metrics.fully_detected_mask(batch.node_mask) * batch.scene_mask[:, None]
        for name, value in metrics.aoe_foe_sums(pred, truth, eval_mask).items():
            add(name, value)
        for name, value in metrics.min_ade_fde_sums(pred, truth, eval_mask).items():
            add(name, value)
        for name, value in metrics.release_spread_sums(pred, truth, eval_mask).items():
            add(name, value)
        if with_kde:
            for name, value in metrics.kde_nll_sums(pred, truth, eval_mask).items():
                add("kde_" + name, value)
        collisions, pairs = metrics.collision_sums(pred, predicted_mask)
        add("pred_collisions", np.sum(collisions))
        add("pred_pairs", np.sum(pairs))
        collisions, pairs = metrics.collision_sums(truth, predicted_mask, truth_step_mask)
        add("truth_collisions", np.sum(collisions))
        add("truth_pairs", np.sum(pairs))
        for name, value in metrics.trajnet_collision_sums(pred, truth, eval_mask, predicted_mask,
                                                          truth_step_mask).items():
            add("trajnet_" + name, value)
        if with_baseline:
            for name, value in _constant_velocity_sums(batch, obs_len, eval_mask).items():
                add("cv_" + name, value)
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
        # The release's "std" (docs/MODEL.md 4): per-window spread across runs, summed.
        "release_aoe_std": float(totals["aoe_window_std_sum"] / max(count, 1.0)),
        "release_foe_std": float(totals["foe_window_std_sum"] / max(count, 1.0)),
        "min_ade": float(totals["min_ade_sum"] / max(count, 1.0)),
        "min_fde": float(totals["min_fde_sum"] / max(count, 1.0)),
        "collision_rate": float(totals["pred_collisions"] / max(totals["pred_pairs"], 1.0)),
        "truth_collision_rate": float(totals["truth_collisions"]
                                      / max(totals["truth_pairs"], 1.0)),
        "col_i": float(np.mean(totals["trajnet_col1_sum"]) / max(count, 1.0)),
        "col_ii": float(np.mean(totals["trajnet_col2_sum"]) / max(count, 1.0)),
    }
    if with_kde:
        result["kde_nll"] = float(totals["kde_nll_sum"] / max(totals["kde_count"], 1.0))
    if with_baseline:
        result["cv_aoe"] = float(totals["cv_aoe_sum"][0] / max(count, 1.0))
        result["cv_foe"] = float(totals["cv_foe_sum"][0] / max(count, 1.0))
    return result


def protocol_line(data_config: DataConfig, split: str, num_samples: int,
                  epochs: int | None = None) -> str:
    trained = f", {epochs} epochs" if epochs is not None else ""
    return (f"{data_config.scene}, protocol {data_config.protocol}, {split} split, "
            f"{num_samples} samples (hard, tau {EVAL_TAU}){trained}")


_HEADER = ("model", "AOE (m)", "FOE (m)", "minADE", "minFDE", "KDE NLL", "collisions",
           "Col-I", "Col-II")


def _rows(result: dict) -> list[tuple[str, ...]]:
    """The table's rows: the model, constant velocity on the same pedestrians, the truth."""
    def percent(rate):
        return f"{100 * rate:.2f}%"

    rows = [("GST" if "epoch" in result else "predictions",
             f"{result['aoe']:.3f} ± {result['aoe_std']:.3f}",
             f"{result['foe']:.3f} ± {result['foe_std']:.3f}",
             f"{result['min_ade']:.3f}", f"{result['min_fde']:.3f}",
             f"{result['kde_nll']:.2f}" if "kde_nll" in result else "-",
             percent(result["collision_rate"]), percent(result["col_i"]),
             percent(result["col_ii"]))]
    if "cv_aoe" in result:
        rows.append(("constant velocity", f"{result['cv_aoe']:.3f}", f"{result['cv_foe']:.3f}",
                     *"-" * 6))
    rows.append(("ground truth", *"-" * 5, percent(result["truth_collision_rate"]), "-", "-"))
    return rows


def format_table(result: dict) -> str:
    """A readable table of one evaluation, the protocol on top."""
    rows = [_HEADER, *_rows(result)]
    widths = [max(len(row[i]) for row in rows) for i in range(len(_HEADER))]
    lines = [result["protocol"], f"{result['pedestrians']} fully detected pedestrians; "
             "collisions: pairs closer than 0.1 m; Col-I / Col-II: TrajNet++'s, against the "
             "predicted / true neighbours", ""]
    lines += ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
              for row in rows]
    return "\n".join(lines)


def format_markdown(result: dict) -> str:
    lines = [f"Protocol: {result['protocol']}; {result['pedestrians']} fully detected pedestrians.",
             "", "| " + " | ".join(_HEADER) + " |", "|---" * len(_HEADER) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in _rows(result)]
    return "\n".join(lines) + "\n"


def _split_windows(data_config: DataConfig, split: str) -> data.WindowSet:
    window_set = data.load_split(data_config, split)
    if not len(window_set):
        raise data.DataError(f"{data_config.scene}: the {split} split has no window")
    return window_set


def evaluate_run(run, data_config: DataConfig, split: str, *, num_samples: int = 20,
                 seed: int = 0, with_kde: bool = True, progress: Progress | None = None,
                 devices: Devices | None = None) -> dict[str, Any]:
    """Evaluate a loaded model (`gst_jax.runs.Run`) on one split: the metrics of
    `evaluate_params` plus what was evaluated (scene, split, windows, epoch, protocol line)."""
    window_set = _split_windows(data_config, split)
    result = evaluate_params(run.params, jax.random.key(seed), window_set, run.model_config,
                             num_samples=num_samples, with_kde=with_kde,
                             fully_detected_only=run.train_config.fully_detected_only,
                             progress=progress, devices=devices)
    result.update(model=run.name, scene=data_config.scene, protocol_name=data_config.protocol,
                  split=split, windows=len(window_set), epoch=run.epoch,
                  output=run.model_config.output, num_edge_heads=run.model_config.num_edge_heads,
                  protocol=protocol_line(data_config, split, num_samples, run.epoch))
    return result


def write_run_predictions(run, data_config: DataConfig, split: str, path: Path, *,
                          num_samples: int = 20, seed: int = 0,
                          progress: Progress | None = None) -> int:
    """Write K sampled futures of every window of the split to a TrajNet++ file (the samples
    `evaluate_run` scores with the same seed); returns the rows written."""
    window_set = _split_windows(data_config, split)
    predicted = predict_windows(run.params, jax.random.key(seed), window_set, run.model_config,
                                num_samples=num_samples,
                                fully_detected_only=run.train_config.fully_detected_only,
                                progress=progress)
    return write_predictions(path, window_set, predicted, run.model_config.obs_len)


def evaluate_prediction_file(path: Path, data_config: DataConfig, split: str, *,
                             obs_len: int = 8, with_kde: bool = True) -> dict[str, Any]:
    """Score a TrajNet++ prediction file (ours or another model's) against a split's windows,
    with the metrics of `evaluate_params`."""
    window_set = _split_windows(data_config, split)
    result = score(read_predictions(path, window_set, obs_len), obs_len=obs_len,
                   with_kde=with_kde)
    result.update(model=str(path), scene=data_config.scene, protocol_name=data_config.protocol,
                  split=split, windows=len(window_set),
                  protocol=protocol_line(data_config, split, result["samples"]))
    return result
