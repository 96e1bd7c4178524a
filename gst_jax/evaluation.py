"""Evaluation with the paper's protocol (docs/MODEL.md 4) and the standard metrics.

Metrics count fully detected pedestrians only. K = 20 hard-sampled predictions of every
window are the paper's "20 runs of the whole test set": run k is sample k of every window,
so AOE/FOE are reported as the mean over runs with the spread (std) across runs. Beside them:
best-of-K minADE/minFDE, KDE NLL (Trajectron++ rule), the collision rate of predictions and
of the ground truth, TrajNet++'s Col-I / Col-II, and a constant-velocity baseline on exactly
the same pedestrians. The same metrics score a TrajNet++ prediction file
(`evaluate_prediction_file`), ours (`write_run_predictions`) or another model's. For a
TrajNet++ file's own scenes (`gst_jax.data.trajnet`), a submission is also scored as
TrajNet++'s evaluator scores it (`gst_jax.trajnet_metrics`), beside these per-pedestrian
figures.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Iterable, Iterator, NamedTuple

import jax
import numpy as np

from gst_jax import data, graph, metrics, trajnet_metrics
from gst_jax.config import EVAL_TAU, DataConfig, ModelConfig, TimeGrid
from gst_jax.data.trajnet import SceneSet, load_scenes, rows_grid
from gst_jax.errors import DataError
from gst_jax.model import Controls, Params
from gst_jax.parallel import Devices
from gst_jax.predict import DEFAULT_MEMORY_BUDGET, make_predict
from gst_jax.prediction_files import (
    PredictedBatch,
    predicted_batches,
    read_prediction_file,
    read_predictions,
    write_predictions,
    write_scene_predictions,
)
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
    """A readable table of one evaluation, the protocol on top; for a TrajNet++ submission,
    TrajNet++'s own figures below."""
    lines = [result["protocol"]]
    if "aoe" in result:
        rows = [_HEADER, *_rows(result)]
        lines += [f"{result['pedestrians']} fully detected pedestrians; collisions: pairs "
                  "closer than 0.1 m; Col-I / Col-II: TrajNet++'s, against the predicted / "
                  "true neighbours", "", *_aligned(rows)]
    if "trajnet" in result:
        lines += ["", *_trajnet_caption(result), "", *_aligned(_trajnet_rows(result["trajnet"]))]
    return "\n".join(lines)


def format_markdown(result: dict) -> str:
    if "aoe" in result:
        lines = [f"Protocol: {result['protocol']}; {result['pedestrians']} fully detected "
                 "pedestrians.", "", *_markdown_rows([_HEADER, *_rows(result)])]
    else:
        lines = [f"Protocol: {result['protocol']}."]
    if "trajnet" in result:
        lines += ["", *_trajnet_caption(result), "",
                  *_markdown_rows(_trajnet_rows(result["trajnet"]))]
    return "\n".join(lines) + "\n"


def _aligned(rows: list[tuple[str, ...]]) -> list[str]:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
            for row in rows]


def _markdown_rows(rows: list[tuple[str, ...]]) -> list[str]:
    return ["| " + " | ".join(rows[0]) + " |", "|---" * len(rows[0]) + "|",
            *("| " + " | ".join(row) + " |" for row in rows[1:])]


_TRAJNET_HEADER = ("TrajNet++", "scenes", "ADE", "FDE", "Top-3 ADE", "Top-3 FDE",
                   "Top-K ADE", "Top-K FDE", "Col-I", "Col-II", "NLL")


def _trajnet_caption(result: dict) -> list[str]:
    """What TrajNet++'s figures are, and why one is missing."""
    trajnet = result["trajnet"]
    lines = [f"TrajNet++'s figures (its evaluator's rules): the primary pedestrian of each of "
             f"the {trajnet['scenes']} scenes; ADE, FDE, Col-I, Col-II of sample 0; Top-k: the "
             f"sample of least ADE among the first k (K = {trajnet['samples']}), its FDE; "
             "Col-I, Col-II: % of scenes; NLL: its mean log-likelihood (higher is better) "
             f"over the first {trajnet['log_likelihood_samples']} samples"]
    if trajnet["col_i_percent"] is None:
        lines.append(f"Col-I not defined (TrajNet++ prints -1): in "
                     f"{trajnet['col_i_undefined_scenes']} scenes the file predicts fewer (or "
                     "more) neighbours than TrajNet++ counts (everyone seen before the first "
                     "predicted row; the model predicts those seen at the last two observed ones)")
    if trajnet["log_likelihood"] is None:
        lines.append(f"NLL not defined: it needs {trajnet['log_likelihood_samples']} samples "
                     "(--samples)" if trajnet["samples"] < trajnet["log_likelihood_samples"]
                     else f"NLL not defined: in {trajnet['log_likelihood_undefined_scenes']} "
                     "scenes no step's samples span a plane (TrajNet++'s evaluator stops)")
    if "per_pedestrian_skipped" in result:
        lines.append(f"gst_jax's per-pedestrian figures not computed: "
                     f"{result['per_pedestrian_skipped']}")
    return lines


def _trajnet_rows(trajnet: dict) -> list[tuple[str, ...]]:
    def number(value, digits=3):
        return "-" if value is None else f"{value:.{digits}f}"

    return [_TRAJNET_HEADER,
            ("predictions", str(trajnet["scenes"]), number(trajnet["ade"]),
             number(trajnet["fde"]), number(trajnet["top3_ade"]), number(trajnet["top3_fde"]),
             number(trajnet["topk_ade"]), number(trajnet["topk_fde"]),
             number(trajnet["col_i_percent"], 2), number(trajnet["col_ii_percent"], 2),
             number(trajnet["log_likelihood"], 2)),
            ("constant velocity", str(trajnet["scenes"]), number(trajnet["cv_ade"]),
             number(trajnet["cv_fde"]), *"-" * 7)]


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


class Written(NamedTuple):
    """What `write_run_predictions` wrote: its rows, and what they answer ('242 TrajNet++
    scenes of lcas.ndjson', '176 windows')."""

    rows: int
    answers: str


def write_run_predictions(run, data_config: DataConfig, split: str, path: Path, *,
                          num_samples: int = 20, seed: int = 0, windows: bool = False,
                          progress: Progress | None = None,
                          memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET) -> Written:
    """Write K sampled futures to a TrajNet++ file: for a TrajNet++ file's own scenes
    (`load_scenes`) a submission its evaluator pairs scene for scene, those of each scene's
    primary and of its neighbours the model predicts; else, or with `windows`, those of every
    window of the split (the samples `evaluate_run` scores with the same seed).
    memory_budget_bytes: see `make_predict`."""
    grid = run.model_config.grid
    scene_set = None if windows else load_scenes(data_config, split, grid)
    window_set = (scene_set.windows if scene_set is not None
                  else _split_windows(data_config, split, grid))
    predicted = predict_windows(run.params, jax.random.key(seed), window_set, run.model_config,
                                num_samples=num_samples,
                                fully_detected_only=run.train_config.fully_detected_only,
                                progress=progress, memory_budget_bytes=memory_budget_bytes)
    if scene_set is None:
        return Written(write_predictions(path, window_set, predicted, grid),
                       f"{len(window_set)} windows")
    return Written(write_scene_predictions(path, scene_set, predicted, grid),
                   f"{len(scene_set)} TrajNet++ scenes of {Path(scene_set.path).name}")


def evaluate_prediction_file(path: Path, data_config: DataConfig, split: str, *,
                             grid: TimeGrid | None = None, with_kde: bool = True,
                             windows: bool = False) -> dict[str, Any]:
    """Score a TrajNet++ prediction file (ours or another model's) on the time grid of the
    predictions, with the metrics of `evaluate_params`: against a split's windows, or, for a
    TrajNet++ file's own scenes (`load_scenes`; not with `windows`), against the windows of
    its scenes, with TrajNet++'s own figures beside them as `result["trajnet"]`. grid: the
    predictions' steps; None: a submission's, one a row of its file (`rows_grid`:
    WILDTRACK's 0.5 s), or the paper's for the windows."""
    if grid is None:
        grid = TimeGrid() if windows else rows_grid(data_config, split)
    scene_set = None if windows else load_scenes(data_config, split, grid)
    if scene_set is not None:
        result = _score_submission(path, scene_set, grid, with_kde)
        window_set = scene_set.windows
    else:
        window_set = _split_windows(data_config, split, grid)
        result = score(read_predictions(path, window_set, grid.obs_len), obs_len=grid.obs_len,
                       with_kde=with_kde)
    result.update(model=str(path), scene=data_config.scene, protocol_name=data_config.protocol,
                  split=split, windows=len(window_set),
                  protocol=protocol_line(data_config, split, result["samples"]))
    return result


def _score_submission(path: Path, scene_set: SceneSet, grid: TimeGrid,
                      with_kde: bool) -> dict[str, Any]:
    """TrajNet++'s figures of a submission and gst_jax's of the scenes' windows (every fully
    detected pedestrian: left out, with the reason, where the file lacks one of them)."""
    file = read_prediction_file(path, scene_set.windows, scene_set.scenes)
    trajnet = trajnet_metrics.score_submission(file, scene_set)
    try:
        result = score(predicted_batches(file, scene_set.windows, grid.obs_len,
                                         scene_set.scenes),
                       obs_len=grid.obs_len, with_kde=with_kde)
    except DataError as error:                  # a file of primaries only, say
        result = {"samples": file.num_samples, "per_pedestrian_skipped": str(error)}
    return {**result, "trajnet": trajnet}
