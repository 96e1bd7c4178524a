"""Flags shared by every command (`--scene`, `--protocol`, `--edge-heads`, `--epochs`,
`--seed`, `--workdir`, `--json`, ...), so that each one means the same thing everywhere."""

from __future__ import annotations

import argparse
import dataclasses

from gst_jax.config import PROTOCOLS, SCENES, DataConfig, ModelConfig, TrainConfig

_TRAIN_DEFAULTS = TrainConfig()


def add_data_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("data")
    group.add_argument("--scene", default="eth", choices=SCENES,
                       help="dataset: an ETH/UCY scene or a TrajNet++ crowd (default: eth)")
    group.add_argument("--protocol", default="paper", choices=PROTOCOLS,
                       help="paper: the release's per-file temporal 80/20 split; paper-val: the "
                            "same with a validation set carved from the end of each file's "
                            "train windows; loo: leave-one-scene-out (ETH/UCY only)")
    group.add_argument("--data-dir", default=None,
                       help="folder holding eth_ucy/ and trajnetpp/ (default: bundled data/)")


def add_model_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("model")
    group.add_argument("--edge-heads", type=int, default=1, choices=(0, 1, 2, 4, 8, 16),
                       help="n, the most neighbours each pedestrian attends to "
                            "(0 = full connection, no Gumbel selector; default: 1)")
    group.add_argument("--no-ghost", action="store_true",
                       help="disable the ghost agent (the 'attend to nobody' neighbour)")
    group.add_argument("--output", default="deterministic", choices=("deterministic", "gaussian"),
                       help="GST (D): displacements; GST (P): bivariate Gaussians (default: D)")
    group.add_argument("--temporal", default="lstm", choices=("lstm", "tcn"),
                       help="lstm: recurrent rollout, interacting at every predicted step "
                            "(paper); tcn: the release's temporal convolution readout of the "
                            "observed steps (default: lstm)")


def add_train_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("training")
    d = _TRAIN_DEFAULTS
    group.add_argument("--epochs", type=int, default=d.epochs, help=f"epochs (default: {d.epochs})")
    group.add_argument("--batch-size", type=int, default=d.batch_size,
                       help=f"scenes averaged per optimiser step (default: {d.batch_size})")
    group.add_argument("--learning-rate", type=float, default=d.learning_rate,
                       help=f"initial Adam learning rate, x{d.lr_decay} every {d.lr_decay_every} "
                            f"epochs (default: {d.learning_rate})")
    group.add_argument("--seed", type=int, default=d.seed, help=f"random seed (default: {d.seed})")
    group.add_argument("--fully-detected-only", action="store_true",
                       help="drop partially detected pedestrians (the paper's 'F' baseline)")
    group.add_argument("--no-rotate", action="store_true", help="disable random rotation")
    group.add_argument("--checkpoint-every", type=int, default=d.checkpoint_every,
                       help=f"epochs between checkpoints (default: {d.checkpoint_every})")
    group.add_argument("--eval-every", type=int, default=d.eval_every,
                       help="epochs between validation AOE/FOE, with a protocol that has a "
                            f"validation split (default: {d.eval_every}; 0 = never)")
    group.add_argument("--max-train-windows", type=int, default=0,
                       help="train on the first k windows only (smoke tests; default: all)")


def add_output_flags(parser: argparse.ArgumentParser, *, workdir_help: str) -> None:
    parser.add_argument("--workdir", default=None, help=workdir_help)
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def data_config(args: argparse.Namespace) -> DataConfig:
    return DataConfig(scene=args.scene, protocol=args.protocol, data_dir=args.data_dir)


def model_config(args: argparse.Namespace) -> ModelConfig:
    return ModelConfig(num_edge_heads=args.edge_heads, ghost=not args.no_ghost,
                       output=args.output, temporal=args.temporal)


def train_config(args: argparse.Namespace) -> TrainConfig:
    return dataclasses.replace(
        _TRAIN_DEFAULTS, epochs=args.epochs, batch_size=args.batch_size,
        learning_rate=args.learning_rate, seed=args.seed,
        fully_detected_only=args.fully_detected_only, rotate=not args.no_rotate,
        checkpoint_every=args.checkpoint_every, eval_every=args.eval_every,
        max_train_windows=args.max_train_windows)


def run_name(data: DataConfig, model: ModelConfig, train: TrainConfig) -> str:
    """A work directory name that identifies a run, so the same command finds it to resume."""
    parts = [data.scene, data.protocol, "d" if model.output == "deterministic" else "p",
             f"n{model.num_edge_heads}"]
    if not model.ghost:
        parts.append("noghost")
    if model.temporal != "lstm":
        parts.append(model.temporal)
    if train.fully_detected_only:
        parts.append("fd")
    parts += [f"e{train.epochs}", f"seed{train.seed}"]
    return "-".join(parts)
