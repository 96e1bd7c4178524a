"""Figures of a trained model: one test window's prediction with its sampled graphs (the
paper's Fig. 3), one agent's selection probabilities over time, and the training curves.

Predictions use the evaluation protocol (hard samples, tau 0.03); figures are drawn from
numpy arrays after the jitted call, never inside it.
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from gst_jax import data, figures
from gst_jax.config import DataConfig
from gst_jax.errors import RunError
from gst_jax.io.workdir import WorkDir
from gst_jax.predict import Prediction, make_predict
from gst_jax.runs import Run


def predict_window(run: Run, data_config: DataConfig, index: int, samples: int, seed: int
                   ) -> tuple[data.Window, data.SceneBatch, Prediction]:
    """K samples (with graphs) of test window `index`, unpadded; arrays as numpy."""
    window_set = data.load_split(data_config, "test", run.model_config.grid)
    if not 0 <= index < len(window_set):
        raise RunError(f"window {index} out of range: {data_config.scene} test has "
                       f"{len(window_set)} windows")
    window = window_set[index]
    batch = data.pad_windows([window], window.num_pedestrians)
    predict = make_predict(run.model_config, num_samples=samples, with_graph=True)
    prediction = jax.tree.map(np.asarray, predict(run.params, jax.random.key(seed), batch))
    return window, batch, prediction


def scene_figure(run: Run, data_config: DataConfig, index: int, out: Path, *, samples: int = 20,
                 seed: int = 0, pdf: bool = False) -> Path:
    """Observed, true and K predicted paths of a test window with the sampled edges of sample
    0, and their selection probabilities, at the last observed step and in the middle of the
    prediction."""
    window, batch, prediction = predict_window(run, data_config, index, samples, seed)
    assert prediction.sampled_adjacency is not None and prediction.edge_probs is not None, (
        "predict_window predicts the graphs")
    heads = max(run.model_config.num_edge_heads, 1)
    selection = prediction.edge_probs[0, 0, :, :, :heads].mean(axis=-2)       # (S, N, N+1)
    obs_len = run.model_config.obs_len
    positions, mask = batch.positions[0], batch.position_mask[0]
    predicted_paths = prediction.positions[:, 0]                           # (K, P, N, 2)
    predicted = prediction.predicted_mask[0] > 0
    middle = (run.model_config.pred_len - 1) // 2
    # A velocity needs both of the last two observed positions (not a zero-filled one).
    velocity = ((positions[obs_len - 1] - positions[obs_len - 2])
                * batch.predicted_mask(obs_len)[0][:, None])
    last_obs = (prediction.sampled_adjacency[0, 0, obs_len - 1], selection[obs_len - 1],
                positions[obs_len - 1], velocity, mask[obs_len - 1] > 0)
    columns, labels = [last_obs], [f"t = {obs_len} (last observed)"]
    if prediction.sampled_adjacency.shape[2] > obs_len:                     # LSTM rollouts
        sample0 = predicted_paths[0]
        previous = sample0[middle - 1] if middle else positions[obs_len - 1]
        columns.append((prediction.sampled_adjacency[0, 0, obs_len + middle],
                        selection[obs_len + middle], sample0[middle],
                        sample0[middle] - previous, predicted))
        labels.append(f"t = {obs_len + middle + 1} (predicted)")
    title = (f"{data_config.scene} test window {index}, {samples} samples, "
             f"n = {run.model_config.num_edge_heads}, epoch {run.epoch}")
    arguments = (positions[:obs_len], mask[:obs_len], positions[obs_len:], mask[obs_len:],
                 predicted_paths, predicted, window.fully_detected(), columns, labels)
    path = figures.scene_prediction(*arguments, out, title)
    if pdf:
        figures.scene_prediction(*arguments, out.with_suffix(".pdf"), title)
    return path


def attention_figure(run: Run, data_config: DataConfig, index: int, agent: int, out: Path, *,
                     seed: int = 0) -> Path:
    """One agent's selection probabilities over its neighbours and the ghost, per step."""
    window, batch, prediction = predict_window(run, data_config, index, 1, seed)
    assert prediction.edge_probs is not None, "predict_window predicts the graphs"
    if not 0 <= agent < window.num_pedestrians:
        raise RunError(f"agent {agent} out of range: the window has {window.num_pedestrians} "
                       "pedestrians")
    n = max(run.model_config.num_edge_heads, 1)
    probabilities = prediction.edge_probs[0, 0, :, agent, :n].mean(axis=1)     # (S, N+1)
    present = batch.position_mask[0].max(axis=0) > 0
    return figures.attention_over_time(
        probabilities, present, agent, run.model_config.obs_len, run.model_config.step_s, out,
        f"{data_config.scene} test window {index}, agent {agent}, epoch {run.epoch}")


def training_figure(workdir: WorkDir, out: Path) -> Path:
    """Loss (and validation AOE/FOE) per epoch from metrics.jsonl."""
    records = workdir.read_metrics()
    if not records:
        raise RunError(f"{workdir.metrics_path} is missing or empty (a work directory of "
                       "gst_jax.train?)")
    return figures.training_curves(records, out, str(workdir.path))
