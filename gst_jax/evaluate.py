"""Evaluate a trained model with the paper's protocol: `python -m gst_jax.evaluate MODEL`.

MODEL is a work directory (or one of its checkpoints), SWEEP_DIR:MEMBER or pretrained:NAME.
K = 20 hard-sampled predictions of every window of the split are the paper's 20 runs; AOE
and FOE are the mean over runs with their spread, on fully detected pedestrians, beside
best-of-K, KDE NLL, collision rates and constant velocity on the same pedestrians. The
result goes to <workdir>/eval/<scene>-<protocol>-<split>-e<epoch>.json and .md.
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.evaluation import evaluate_run, format_markdown, format_table
from gst_jax.progress import Progress
from gst_jax.runs import WorkDir, load_model


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.evaluate", __doc__)
    parser.add_argument("model", help="a work directory of `python -m gst_jax.train` (or one of "
                        "its checkpoints/<epoch>), SWEEP_DIR:MEMBER, or pretrained:NAME")
    cli.add_data_flags(parser, of_run=True)
    parser.add_argument("--split", default="test", choices=("test", "val", "train", "all"),
                        help="which split to evaluate; all: every window (default: test)")
    parser.add_argument("--samples", type=cli.positive_int, default=20,
                        help="K: runs of the paper protocol / samples for best-of-K and KDE")
    parser.add_argument("--seed", type=int, default=0, help="seed of the evaluation samples")
    parser.add_argument("--epoch", type=int, default=None,
                        help="checkpoint epoch (default: latest)")
    parser.add_argument("--no-kde", action="store_true", help="skip the KDE NLL")
    parser.add_argument("--markdown", default=None, help="also write a markdown table here")
    cli.add_output_flags(parser, workdir_help="where eval/ is written (default: the model's "
                         "own work directory; a shipped model's result is only printed)")
    cli.run(evaluate, parser, argv)


def evaluate(args) -> None:
    run = load_model(args.model, args.epoch)
    out = WorkDir(args.workdir) if args.workdir else run.workdir
    if out is not None:
        out.check_writable()
    data_config = cli.data_config(args, base=run.data_config)
    result = evaluate_run(run, data_config, args.split, num_samples=args.samples,
                          seed=args.seed, with_kde=not args.no_kde, progress=Progress())
    print(json.dumps(result, indent=2) if args.json else format_table(result), flush=True)
    markdown = format_markdown(result)
    if args.markdown:
        Path(args.markdown).write_text(markdown)
    if out is not None:
        written = out.write_evaluation(data_config, args.split, run.epoch, result, markdown)
        cli.say(f"\nwritten: {written}, .md")


if __name__ == "__main__":
    main()
