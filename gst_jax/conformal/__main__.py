"""Play a scene as a stream and measure conformal regions around a model's predictions:
`python -m gst_jax.conformal MODEL --scene eth --method dtaci --alpha 0.1`.

The split's frames (default: the test split of --scene, or of --data with --fps/--units)
are fed one model step at a time (`gst_jax.stream`); every prediction (the mean mode) is
scored k steps later by its distance to the observed position. split: calibrated on the first
--calibration of the frames, then fixed; aci / dtaci / pid: updated online from the scores as
they arrive. Reported on the frames after --calibration: per horizon step the coverage (the
fraction within the radius issued with them), the mean radius and ACI's finite-stream bound;
then the share of predictions with every step inside its disc.
"""

from __future__ import annotations

import itertools
import json

from gst_jax import cli
from gst_jax.coverage import METHODS, play, scene_streams
from gst_jax.coverage_report import draw, format_table
from gst_jax.progress import Progress
from gst_jax.runs import load_model


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.conformal", __doc__, compilation_cache=True)
    parser.add_argument("model", help="a work directory of `python -m gst_jax.train`, "
                        "SWEEP_DIR:MEMBER, or pretrained:NAME")
    cli.add_data_flags(parser, of_run=True)
    parser.add_argument("--split", default="test", choices=("test", "val", "train", "all"),
                        help="which split's frames to play (default: test)")
    parser.add_argument("--method", default="dtaci", choices=METHODS, help="split conformal, "
                        "ACI (Gibbs & Candes 2021), DtACI (2022, GenSafeNav's variant) or PID "
                        "(Angelopoulos et al. 2023) (default: dtaci)")
    parser.add_argument("--alpha", type=cli.open_fraction, default=0.1,
                        help="target miscoverage: discs should hold 1 - alpha (default: 0.1)")
    parser.add_argument("--calibration", type=cli.open_fraction, default=0.3, metavar="FRACTION",
                        help="the first fraction of the frames: split's calibration, and left "
                             "out of every method's figures (default: 0.3)")
    parser.add_argument("--bonferroni", action="store_true", help="aim each step at alpha / P: "
                        "a prediction's P discs hold together with probability 1 - alpha")
    parser.add_argument("--per-track", action="store_true", help="aci/dtaci per track and "
                        "horizon step, as GenSafeNav's ROS 2 node (default: pooled per step)")
    parser.add_argument("--max-frames", type=cli.positive_int, default=None,
                        help="each file's first frames only, a quick look (default: all)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the graphs sampled and "
                        "of DtACI's expert draws (default: 0)")
    parser.add_argument("--figure", metavar="PNG", help="draw one frame's discs and the coverage")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    cli.run(measure, parser, argv)


def measure(args) -> None:
    run = load_model(args.model)
    data_config = cli.data_config(args, base=run.data_config)
    streams = [itertools.islice(s, args.max_frames)
               for s in scene_streams(data_config, args.split, run.model_config.grid)]
    result, snapshot = play(run, streams, method=args.method, alpha=args.alpha,
                            pooled=not args.per_track, calibration=args.calibration,
                            seed=args.seed, bonferroni=args.bonferroni, progress=Progress())
    result.update(model=run.name, scene=data_config.scene, split=args.split)
    if args.figure and snapshot:
        draw(snapshot, result, args.figure, f"{run.name} on {data_config.scene} ({args.split}), "
             f"{args.method}, alpha {args.alpha}, frame {snapshot.frame}")
        cli.say(f"written: {args.figure}")
    print(json.dumps(result, indent=1) if args.json else format_table(result))


if __name__ == "__main__":
    main()
