"""Figures of a trained run: `scene` (the paper's Fig. 3), `attention`, `training`.

    python -m gst_jax.plot scene runs/eth-paper-d-n1-e200-seed1000 --window 10
    python -m gst_jax.plot attention runs/eth-paper-d-n1-e200-seed1000 --window 10 --agent 0
    python -m gst_jax.plot training runs/eth-paper-d-n1-e200-seed1000

Predictions use the evaluation protocol (hard samples, tau 0.03); figures are drawn with
numpy arrays after the jitted call, never inside it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import jax
import numpy as np

from gst_jax import data, figures
from gst_jax.config import PROTOCOLS, SCENES
from gst_jax.evaluate import load_run
from gst_jax.predict import make_predict


def _predict_window(run, scene: str | None, protocol: str | None, index: int, samples: int,
                    seed: int):
    data_config = dataclasses.replace(run.data_config, scene=scene or run.data_config.scene,
                                      protocol=protocol or run.data_config.protocol)
    window_set = data.load_split(data_config, "test")
    if not 0 <= index < len(window_set):
        raise SystemExit(f"error: --window {index} out of range: {data_config.scene} test has "
                         f"{len(window_set)} windows")
    window = window_set[index]
    batch = data.pad_windows([window], window.num_pedestrians)
    predict = make_predict(run.model_config, num_samples=samples, with_graph=True)
    prediction = jax.tree.map(np.asarray, predict(run.params, jax.random.key(seed), batch))
    return data_config, window, batch, prediction


def scene(args) -> Path:
    run = load_run(args.run)
    data_config, window, batch, prediction = _predict_window(
        run, args.scene, args.protocol, args.window, args.samples, args.seed)
    obs_len = run.model_config.obs_len
    positions, mask = batch.positions[0], batch.position_mask[0]
    samples = prediction.positions[:, 0]                                   # (K, P, N, 2)
    predicted = prediction.predicted_mask[0] > 0
    # Graphs of sample 0: at the last observed step and in the middle of the prediction.
    middle = (run.model_config.pred_len - 1) // 2
    last_obs = (prediction.sampled_adjacency[0, 0, obs_len - 1], positions[obs_len - 1],
                positions[obs_len - 1] - positions[obs_len - 2], mask[obs_len - 1] > 0)
    columns, labels = [last_obs], [f"t = {obs_len} (last observed)"]
    if prediction.sampled_adjacency.shape[2] > obs_len:                     # LSTM rollouts
        step = obs_len + middle
        sample0 = samples[0]
        columns.append((prediction.sampled_adjacency[0, 0, step], sample0[middle],
                        sample0[middle] - (sample0[middle - 1] if middle else positions[obs_len - 1]),
                        predicted))
        labels.append(f"t = {obs_len + middle + 1} (predicted)")
    title = (f"{data_config.scene} test window {args.window}, {args.samples} samples, "
             f"n = {run.model_config.num_edge_heads}, epoch {run.epoch}")
    out = Path(args.out or run.workdir / "figures" / f"scene-{data_config.scene}-{args.window}.png")
    path = figures.scene_prediction(
        positions[:obs_len], mask[:obs_len], positions[obs_len:], mask[obs_len:], samples,
        predicted, window.fully_detected(), columns, labels, out, title)
    if args.pdf:
        figures.scene_prediction(
            positions[:obs_len], mask[:obs_len], positions[obs_len:], mask[obs_len:], samples,
            predicted, window.fully_detected(), columns, labels, out.with_suffix(".pdf"), title)
    return path


def attention(args) -> Path:
    run = load_run(args.run)
    data_config, window, batch, prediction = _predict_window(
        run, args.scene, args.protocol, args.window, 1, args.seed)
    if not 0 <= args.agent < window.num_pedestrians:
        raise SystemExit(f"error: --agent {args.agent} out of range: the window has "
                         f"{window.num_pedestrians} pedestrians")
    n = max(run.model_config.num_edge_heads, 1)
    probabilities = prediction.edge_probs[0, 0, :, args.agent, :n].mean(axis=1)   # (S, N+1)
    present = batch.position_mask[0].max(axis=0) > 0
    out = Path(args.out or run.workdir / "figures" /
               f"attention-{data_config.scene}-{args.window}-agent{args.agent}.png")
    return figures.attention_over_time(
        probabilities, present, args.agent, run.model_config.obs_len, out,
        f"{data_config.scene} test window {args.window}, agent {args.agent}, epoch {run.epoch}")


def training(args) -> Path:
    metrics_path = Path(args.run) / "metrics.jsonl"
    if not metrics_path.exists():
        raise SystemExit(f"error: {metrics_path} not found (a work directory of gst_jax.train?)")
    records = [json.loads(line) for line in metrics_path.read_text().splitlines() if line.strip()]
    if not records:
        raise SystemExit(f"error: {metrics_path} is empty")
    out = Path(args.out or Path(args.run) / "figures" / "training.png")
    return figures.training_curves(records, out, str(args.run))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m gst_jax.plot",
                                     description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for name, help_text in (("scene", "observed, true and K predicted paths, sampled graphs and "
                             "adjacency matrices of one test window (Fig. 3)"),
                            ("attention", "one agent's selection probabilities over its "
                             "neighbours and the ghost, per step"),
                            ("training", "loss (and validation AOE/FOE) per epoch")):
        sub = commands.add_parser(name, help=help_text, description=help_text)
        sub.add_argument("run", help="work directory of `python -m gst_jax.train`")
        sub.add_argument("--out", default=None, help="PNG path (default: <run>/figures/...)")
        if name == "training":
            continue
        sub.add_argument("--scene", default=None, choices=SCENES,
                         help="scene (default: the run's own)")
        sub.add_argument("--protocol", default=None, choices=PROTOCOLS,
                         help="split protocol (default: the run's own)")
        sub.add_argument("--window", type=int, default=0, help="test window index (default: 0)")
        sub.add_argument("--seed", type=int, default=0, help="seed of the samples (default: 0)")
        if name == "scene":
            sub.add_argument("--samples", type=int, default=20, help="K (default: 20)")
            sub.add_argument("--pdf", action="store_true", help="also write a PDF")
        else:
            sub.add_argument("--agent", type=int, default=0, help="pedestrian index (default: 0)")
    args = parser.parse_args(argv)
    path = {"scene": scene, "attention": attention, "training": training}[args.command](args)
    print(f"written: {path}", file=sys.stderr)


if __name__ == "__main__":
    main()
