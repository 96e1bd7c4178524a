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
from gst_jax.config import EVAL_TAU, DataConfig, ModelConfig, TimeGrid
from gst_jax.errors import DataError
from gst_jax.model import Controls, Params
from gst_jax.parallel import Devices
from gst_jax.predict import DEFAULT_MEMORY_BUDGET, make_predict
from gst_jax.prediction_files import PredictedBatch, read_predictions, write_predictions
from gst_jax.progress import Progress


def evaluate_params(params: Params, key: jax.Array, window_set: data.WindowSet,
                    config: ModelConfig, *, num_samples: int = 20,
                    with_kde: bool = True, with_baseline: bool = True,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None, progress: Progress | None = None,
                    devices: Devices | None = None) -> dict[str, Any]:
    """Evaluate `params` on every window of `window_set`; returns a flat dict of metrics.

    The arguments are those of `predict_windows`; with_kde / with_baseline: also the KDE NLL /
    the constant-velocity baseline.
    """
    predicted = predict_windows(params, key, window_set, config, num_samples=num_samples,
                                fully_detected_only=fully_detected_only,
                                controls=controls, predict=predict, progress=progress,
                                devices=devices)
    return score(predicted, obs_len=config.obs_len, with_kde=with_kde,
                 with_baseline=with_baseline)


def predict_windows(params: Params, key: jax.Array, window_set: data.WindowSet,
                    config: ModelConfig, *, num_samples: int = 20,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None, progress: Progress | None = None,
                    devices: Devices | None = None,
                    memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET
                    ) -> Iterator[PredictedBatch]:
    """K sampled futures of every window, batch by batch (`data.evaluation_batches`).

    Sample k of a window depends on the key, k and the window's index only (`noise`), not
    on its batch: the same key gives the same samples whatever the batching or the devices,
    to an evaluation and to a prediction file alike. fully_detected_only: the model observes
    fully detected pedestrians only (a run trained with the "F" baseline is tested the same
    way). controls: traced n / ghost overriding the config's (sweeps), at tau = EVAL_TAU.
    predict: a `make_predict(config, num_samples, with_graph=False)` to reuse across calls
    (one compile per bucket for many members). progress: reports the windows predicted, with
    an ETA. devices: the scenes of each batch are split over them. memory_budget_bytes: what
    one batch's program may use, without `predict` (`make_predict`).
    """
    predict = predict or make_predict(config, num_samples=num_samples, with_graph=False,
                                      memory_budget_bytes=memory_budget_bytes)
    if devices is not None:
        params, key, controls = devices.replicate((params, key, controls))
    started, done = time.perf_counter(), 0
    for batch in data.evaluation_batches(window_set,
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
    """The metrics of sampled futures against the windows' own (`metrics.METRICS`): AOE/FOE
    per run, best-of-K, KDE NLL, collisions (0.1 m, and TrajNet++'s Col-I / Col-II),
    constant velocity."""
    names = [name for name in metrics.METRICS if (with_kde or name != "kde_nll")
             and (with_baseline or name not in metrics.BASELINES)]
    totals, num_samples = _score(predicted, obs_len, names)
    return {"pedestrians": int(totals["aoe"].count), "samples": num_samples,
            **metrics.summarize(totals)}


def constant_velocity_baseline(window_set: data.WindowSet, *,
                               grid: TimeGrid = TimeGrid()) -> dict[str, Any]:
    """The constant-velocity column of `evaluate_params` without a model: AOE/FOE on the
    fully detected pedestrians of `window_set` (same windows, same pedestrians)."""
    batches = (PredictedBatch(batch, None, batch.predicted_mask(grid.obs_len))
               for batch in data.evaluation_batches(window_set))
    totals, _ = _score(batches, grid.obs_len, metrics.BASELINES)
    return {"pedestrians": int(totals["cv_aoe"].count), **metrics.summarize(totals)}


def _score(predicted: Iterable[PredictedBatch], obs_len: int, names: Iterable[str]
           ) -> tuple[dict[str, metrics.Ratio], int]:
    """The summed ratios of the metrics `names` over every batch, and K."""
    totals: dict[str, metrics.Ratio] = {}
    num_samples = 0
    for batch, pred, predicted_mask in predicted:                    # pred (K, B, P, N, 2)
        num_samples = 0 if pred is None else pred.shape[0]
        scene_mask = batch.scene_mask
        scored = metrics.Scored(
            pred=pred, truth=np.asarray(batch.positions[:, obs_len:]),
            scored_mask=batch.fully_detected_mask * scene_mask[:, None],
            predicted_mask=predicted_mask,
            truth_step_mask=np.asarray(batch.position_mask[:, obs_len:]
                                       * scene_mask[:, None, None]),
            observed=np.asarray(batch.positions[:, :obs_len]),
            observed_node_mask=np.asarray(batch.node_mask[:, :obs_len]))
        for name in names:
            metrics.accumulate(totals, metrics.METRICS[name](scored))
    return totals, num_samples


def protocol_line(data_config: DataConfig, split: str, num_samples: int,
                  epochs: int | None = None) -> str:
    """What was evaluated, in one line. epochs: the model's; None for a prediction file,
    whose samples were drawn however its maker drew them: the line claims no sampling."""
    where = f"{data_config.scene}, protocol {data_config.protocol}, {split} split"
    if epochs is None:
        return f"{where}, {num_samples} samples per pedestrian as the file holds them"
    return f"{where}, {num_samples} samples (hard, tau {EVAL_TAU}), {epochs} epochs"


_HEADER = ("model", "AOE (m)", "FOE (m)", "minADE", "minFDE", "KDE NLL", "collisions",
           "Col-I", "Col-II")


def _rows(result: dict) -> list[tuple[str, ...]]:
    """The table's rows: the model, constant velocity on the same pedestrians, the truth."""
    def percent(rate):
        return f"{100 * rate:.2f}%"

    rows: list[tuple[str, ...]] = [
        ("GST" if "epoch" in result else "predictions",
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


def _split_windows(data_config: DataConfig, split: str, grid: TimeGrid) -> data.WindowSet:
    window_set = data.load_split(data_config, split, grid)
    if not len(window_set):
        raise DataError(f"{data_config.scene}: the {split} split has no window")
    return window_set


def evaluate_run(run, data_config: DataConfig, split: str, *, num_samples: int = 20,
                 seed: int = 0, with_kde: bool = True, max_windows: int = 0,
                 progress: Progress | None = None,
                 devices: Devices | None = None) -> dict[str, Any]:
    """Evaluate a loaded model (`gst_jax.runs.Run`) on one split (its first `max_windows`
    windows where set, a quick look): the metrics of `evaluate_params` plus what was
    evaluated (scene, split, windows, epoch, protocol line)."""
    window_set = _split_windows(data_config, split, run.model_config.grid)
    if max_windows:
        window_set = window_set.subset(range(min(max_windows, len(window_set))))
        split = f"{split} (first {len(window_set)} windows)"
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
                          progress: Progress | None = None,
                          memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET) -> int:
    """Write K sampled futures of every window of the split to a TrajNet++ file (the samples
    `evaluate_run` scores with the same seed); returns the rows written. memory_budget_bytes:
    see `make_predict`."""
    window_set = _split_windows(data_config, split, run.model_config.grid)
    predicted = predict_windows(run.params, jax.random.key(seed), window_set, run.model_config,
                                num_samples=num_samples,
                                fully_detected_only=run.train_config.fully_detected_only,
                                progress=progress, memory_budget_bytes=memory_budget_bytes)
    return write_predictions(path, window_set, predicted, run.model_config.grid)


def evaluate_prediction_file(path: Path, data_config: DataConfig, split: str, *,
                             grid: TimeGrid = TimeGrid(), with_kde: bool = True
                             ) -> dict[str, Any]:
    """Score a TrajNet++ prediction file (ours or another model's) against a split's windows
    on the time grid of the predictions, with the metrics of `evaluate_params`."""
    window_set = _split_windows(data_config, split, grid)
    result = score(read_predictions(path, window_set, grid.obs_len), obs_len=grid.obs_len,
                   with_kde=with_kde)
    result.update(model=str(path), scene=data_config.scene, protocol_name=data_config.protocol,
                  split=split, windows=len(window_set),
                  protocol=protocol_line(data_config, split, result["samples"]))
    return result
