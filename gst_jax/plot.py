"""Figures of a trained run: `scene` (the paper's Fig. 3), `attention`, `training`.

    python -m gst_jax.plot scene runs/eth-paper-d-n1-e200-seed1000 --window 10
    python -m gst_jax.plot attention runs/eth-paper-d-n1-e200-seed1000 --window 10 --agent 0
    python -m gst_jax.plot training runs/eth-paper-d-n1-e200-seed1000
"""

from __future__ import annotations

from pathlib import Path

from gst_jax import cli, run_figures
from gst_jax.io.workdir import WorkDir
from gst_jax.runs import load_model

COMMANDS = {
    "scene": "observed, true and K predicted paths of one test window, and sample 0's sampled "
             "edges with their selection probabilities (Fig. 3)",
    "attention": "one agent's selection probabilities over its neighbours and the ghost, per step",
    "training": "loss (and validation AOE/FOE) per epoch"}


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.plot", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    for name, help_text in COMMANDS.items():
        sub = commands.add_parser(name, help=help_text, description=help_text)
        sub.add_argument("run", help="a work directory of `python -m gst_jax.train`" + (
            "" if name == "training" else ", SWEEP_DIR:MEMBER or pretrained:NAME"))
        sub.add_argument("--out", default=None, help="PNG path (default: <run>/figures/...)")
        if name == "training":
            continue
        cli.add_data_flags(sub, of_run=True)
        sub.add_argument("--window", type=int, default=0, help="test window index (default: 0)")
        sub.add_argument("--seed", type=int, default=0, help="seed of the samples (default: 0)")
        if name == "scene":
            sub.add_argument("--samples", type=cli.positive_int, default=20,
                             help="K (default: 20)")
            sub.add_argument("--pdf", action="store_true", help="also write a PDF")
        else:
            sub.add_argument("--agent", type=int, default=0, help="pedestrian index (default: 0)")
    cli.run(plot, parser, argv)


def plot(args) -> None:
    if args.command == "training":
        workdir = WorkDir(args.run)
        path = run_figures.training_figure(workdir, Path(args.out or workdir.figures
                                                         / "training.png"))
    else:
        run = load_model(args.run)
        data_config = cli.data_config(args, base=run.data_config)
        stem = f"{args.command}-{data_config.scene}-{args.window}"
        if args.command == "scene":
            out = Path(args.out or run.figures / f"{stem}.png")
            path = run_figures.scene_figure(run, data_config, args.window, out,
                                            samples=args.samples, seed=args.seed, pdf=args.pdf)
        else:
            out = Path(args.out or run.figures / f"{stem}-agent{args.agent}.png")
            path = run_figures.attention_figure(run, data_config, args.window, args.agent, out,
                                                seed=args.seed)
    cli.say(f"written: {path}")


if __name__ == "__main__":
    main()
