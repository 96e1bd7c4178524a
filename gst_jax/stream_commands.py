"""The stream's commands: `python -m gst_jax.stream replay`.

    python -m gst_jax.stream replay IN.mcap --out OUT.mcap --model pretrained:crowdnav_sj

`replay`: the tracked people of a ROS 2 bag (MCAP, people_msgs/msg/People on --topic) through
a stream, each message at its header stamp; written: a bag of its predictions (/gst/predictions)
and conformal discs (/gst/discs) as visualization_msgs/msg/MarkerArray, in the input's frame and
stamps, for Foxglove or RViz. No ROS needed: pip install "gst_jax[ros]" (docs/robot.md,
"Replaying a ROS 2 bag"; gst_jax.io.ros2).
"""

from __future__ import annotations

import json

from gst_jax import cli
from gst_jax.conformal import ONLINE_METHODS, Regions
from gst_jax.io import ros2
from gst_jax.progress import Progress
from gst_jax.runs import load_model


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.stream", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    replay = commands.add_parser("replay", help="a bag of tracked people -> a bag of "
                                 "predictions and discs")
    add = replay.add_argument
    add("bag", metavar="IN.mcap", help="a ROS 2 bag in MCAP format")
    add("--out", required=True, metavar="OUT.mcap", help="the bag to write")
    add("--model", default="pretrained:crowdnav_sj", type=cli.model_spec,
        help="pretrained:NAME or a run directory (default: %(default)s, CrowdNav++'s "
        "predictor: 0.25 s steps)")
    add("--regions", choices=(*ONLINE_METHODS, "none"), default="dtaci",
        help="the conformal discs' online method, or none (default: dtaci)")
    add("--alpha", type=cli.open_fraction, default=0.1, help="the discs' miscoverage "
        "(default: 0.1)")
    add("--topic", default=ros2.PEOPLE_TOPIC, help=f"the topic of {ros2.PEOPLE} "
        "(default: %(default)s)")
    add("--json", action="store_true", help="print the result as JSON on stdout")
    cli.add_compilation_cache_flag(replay)
    cli.run(stream_command, parser, argv)


def stream_command(args) -> None:
    regions = None if args.regions == "none" else Regions(args.regions, args.alpha)
    run = load_model(args.model)
    summary = ros2.replay(run, args.bag, args.out, topic=args.topic, regions=regions,
                          progress=Progress())
    summary["model"] = run.name
    skipped = f" ({summary['skipped']} skipped)" if summary["skipped"] else ""
    print(json.dumps(summary, indent=2) if args.json else
          f"written: {summary['out']}: {summary['frames']} frames{skipped}, "
          f"{summary['people']} people, "
          f"{summary['predictions']} predictions, {summary['discs']} discs "
          f"({', '.join(f'{t}: {n}' for t, n in summary['topics'].items())})")
