"""Evaluate a trained model with the paper's protocol: `python -m gst_jax.evaluate MODEL`.

MODEL is a work directory (or one of its checkpoints), SWEEP_DIR:MEMBER or pretrained:NAME. K = 20
hard-sampled predictions of every window are the paper's 20 runs: AOE and FOE (mean over runs, with
their spread) on fully detected pedestrians beside best-of-K, KDE NLL, collisions, TrajNet++'s
Col-I / Col-II and constant velocity on the same pedestrians, written to <workdir>/eval/
<scene>-<protocol>-<split>-e<epoch>.json and .md (-k<K> before .json where --samples is not 20).
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.errors import RunError
from gst_jax.evaluation import evaluate_prediction_file, evaluate_run, format_markdown, format_table
from gst_jax.io.workdir import WorkDir
from gst_jax.progress import Progress
from gst_jax.runs import load_model


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.evaluate", __doc__, compilation_cache=True)
    parser.add_argument("model", nargs="?", help="a work directory of `python -m gst_jax.train` "
                        "(or one of its checkpoints/<epoch>), SWEEP_DIR:MEMBER, or pretrained:NAME")
    parser.add_argument("--predictions", metavar="FILE", help="instead of a model, score this "
                        "TrajNet++ prediction file on --data or --scene")
    cli.add_windows_flag(parser, scoring=True)
    cli.add_data_flags(parser, of_run=True)
    cli.add_sampling_flags(parser)
    parser.add_argument("--no-kde", action="store_true", help="skip the KDE NLL")
    parser.add_argument("--max-windows", type=cli.count, default=0, help="the split's first k "
                        "windows only, a quick look, printed not written (default: all)")
    parser.add_argument("--markdown", default=None, help="also write a markdown table here")
    cli.add_device_flags(parser)
    cli.add_output_flags(parser, workdir_help="where eval/ is written (default: the model's "
                         "own work directory; a shipped model's result is only printed)")
    cli.run(evaluate, parser, argv)


def evaluate(args) -> None:
    if (args.model is None) == (args.predictions is None):
        raise RunError("give either a MODEL or --predictions FILE")
    if args.predictions:                          # another model's file, or ours
        data_config, out = cli.data_config(args), None
        result = evaluate_prediction_file(Path(args.predictions), data_config, args.split,
                                          with_kde=not args.no_kde, windows=args.windows)
    else:
        devices = cli.devices(args)             # first: processes join before jax is used
        run = load_model(args.model, args.epoch).with_candidates(args.candidates)
        out = None if args.max_windows or args.candidates is not None else (  # printed only
            WorkDir(args.workdir) if args.workdir else run.workdir)
        if out is not None:
            out.check_writable()
        data_config = cli.data_config(args, base=run.data_config)
        result = evaluate_run(run, data_config, args.split, num_samples=args.samples,
                              seed=args.seed, with_kde=not args.no_kde,
                              max_windows=args.max_windows, progress=Progress(), devices=devices)
    print(json.dumps(result, indent=2) if args.json else format_table(result), flush=True)
    markdown = format_markdown(result)
    if args.markdown:
        Path(args.markdown).write_text(markdown)
    if out is not None:
        written = out.write_evaluation(data_config, args.split, result["epoch"], result, markdown)
        cli.say(f"\nwritten: {written}, .md")


if __name__ == "__main__":
    main()
