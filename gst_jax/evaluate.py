"""Evaluation with the paper's protocol (MODEL.md section 4) and the standard metrics.

Metrics count fully detected pedestrians only. K = 20 hard-sampled predictions of every
window are the paper's "20 runs of the whole test set": run k is sample k of every window,
so AOE/FOE are reported as the mean over runs with the spread (std) across runs. Beside them:
best-of-K minADE/minFDE, KDE NLL (Trajectron++ rule), the collision rate of predictions and
of the ground truth, and a constant-velocity baseline on exactly the same pedestrians.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np

from gst_jax import data, graph, metrics
from gst_jax.checkpoints import Checkpointer
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.model import Controls
from gst_jax.predict import make_predict

# Scenes whose batches of (padded) pedestrians fit this many padded edges share one program.
DEFAULT_EDGE_BUDGET = 16 * 32 * 32


def evaluate_params(params, model_config: ModelConfig, window_set, key: jax.Array, *,
                    num_samples: int = 20, edge_budget: int = DEFAULT_EDGE_BUDGET,
                    with_kde: bool = True, with_baseline: bool = True,
                    fully_detected_only: bool = False, controls: Controls | None = None,
                    predict=None) -> dict[str, Any]:
    """Evaluate `params` on every window of `window_set`; returns a flat dict of metrics.

    fully_detected_only: the model observes fully detected pedestrians only (a run trained
    with the "F" baseline is tested the same way). controls: traced n / ghost overriding the
    config's (sweeps), with tau = 0.03. predict: a `make_predict(model_config, num_samples,
    with_graph=False)` to reuse across calls (one compile per bucket for many members).
    """
    predict = predict or make_predict(model_config, num_samples=num_samples, with_graph=False)
    # scipy's 2-D KDE needs more samples than dimensions; with K <= 2 there is no KDE NLL.
    with_kde = with_kde and num_samples > 2
    obs_len = model_config.obs_len
    totals: dict[str, Any] = {}

    def add(name, value):
        totals[name] = totals.get(name, 0.0) + np.asarray(value, dtype=np.float64)

    batches = data.evaluation_batches(window_set, edge_budget=edge_budget)
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
    return _summarize(totals, num_samples, with_kde, with_baseline)


def constant_velocity_baseline(window_set, *, obs_len: int = 8) -> dict[str, Any]:
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


@dataclasses.dataclass(frozen=True)
class Run:
    """A trained run read back from its work directory."""

    workdir: Path
    model_config: ModelConfig
    data_config: DataConfig
    train_config: TrainConfig
    params: Any
    epoch: int


def load_run(path: str | Path, epoch: int | None = None) -> Run:
    """Read a work directory, its checkpoints/ folder or one checkpoints/<epoch>."""
    from gst_jax.train import create_train_state

    workdir = Path(path)
    if workdir.name.isdigit() and workdir.parent.name == "checkpoints":
        epoch = int(workdir.name) if epoch is None else epoch
        workdir = workdir.parent.parent
    elif workdir.name == "checkpoints":
        workdir = workdir.parent
    checkpointer = Checkpointer(workdir)
    if checkpointer.latest_epoch is None:
        raise SystemExit(f"error: no checkpoint in {workdir} (expected {workdir}/checkpoints/<epoch>)")
    config = checkpointer.read_config(epoch)
    model_config = ModelConfig(**config["model"])
    like = create_train_state(model_config, jax.random.key(0))
    state, _, epoch = checkpointer.restore(like, epoch)
    checkpointer.close()
    return Run(workdir=workdir, model_config=model_config,
               data_config=DataConfig(**config["data"]),
               train_config=TrainConfig(**config["train"]), params=state.params, epoch=epoch)


def protocol_line(data_config: DataConfig, split: str, num_samples: int, epochs: int) -> str:
    return (f"{data_config.scene}, protocol {data_config.protocol}, {split} split, "
            f"{num_samples} samples (hard, tau 0.03), {epochs} epochs")


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


def main(argv: list[str] | None = None) -> None:
    import argparse

    from gst_jax.config import PROTOCOLS, SCENES

    parser = argparse.ArgumentParser(prog="python -m gst_jax.evaluate",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", default=None,
                        help="a work directory of `python -m gst_jax.train`, or one of its "
                             "checkpoints (checkpoints/<epoch>)")
    parser.add_argument("--workdir", default=None, help="same as the positional RUN")
    parser.add_argument("--scene", default=None, choices=SCENES,
                        help="scene to evaluate on (default: the run's own scene)")
    parser.add_argument("--protocol", default=None, choices=PROTOCOLS,
                        help="split protocol (default: the run's own protocol)")
    parser.add_argument("--split", default="test", choices=("test", "val", "train"),
                        help="which split to evaluate (default: test)")
    parser.add_argument("--samples", type=int, default=20,
                        help="K: runs of the paper protocol / samples for best-of-K and KDE")
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation samples")
    parser.add_argument("--epoch", type=int, default=None, help="checkpoint epoch (default: latest)")
    parser.add_argument("--no-kde", action="store_true", help="skip the KDE NLL")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    parser.add_argument("--markdown", default=None, help="also write a markdown table here")
    args = parser.parse_args(argv)
    run_path = args.run or args.workdir
    if run_path is None:
        parser.error("give a work directory (positional RUN or --workdir)")

    run = load_run(run_path, args.epoch)
    data_config = dataclasses.replace(run.data_config, scene=args.scene or run.data_config.scene,
                                      protocol=args.protocol or run.data_config.protocol)
    window_set = data.load_split(data_config, args.split)
    result = evaluate_params(run.params, run.model_config, window_set, jax.random.key(args.seed),
                             num_samples=args.samples, with_kde=not args.no_kde,
                             fully_detected_only=run.train_config.fully_detected_only)
    result.update(scene=data_config.scene, protocol_name=data_config.protocol, split=args.split,
                  windows=len(window_set), epoch=run.epoch, output=run.model_config.output,
                  num_edge_heads=run.model_config.num_edge_heads,
                  protocol=protocol_line(data_config, args.split, args.samples, run.epoch))
    out_dir = run.workdir / "eval"
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{data_config.scene}-{data_config.protocol}-{args.split}-e{run.epoch}"
    (out_dir / f"{stem}.json").write_text(json.dumps(result, indent=2) + "\n")
    (out_dir / f"{stem}.md").write_text(format_markdown(result))
    if args.markdown:
        Path(args.markdown).write_text(format_markdown(result))
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(format_table(result))
        print(f"\nwritten: {out_dir / stem}.json, .md", file=sys.stderr)


if __name__ == "__main__":
    main()
