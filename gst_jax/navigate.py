"""Robot navigation in CrowdNav++'s task with GST in the loop: `python -m gst_jax.navigate`.

    python -m gst_jax.navigate evaluate --planner mpc --episodes 500 --gif 3

`evaluate`: a planner in `simulate.crowdnav.environment.CrowdNav` over many episodes (seeded
from 1000, CrowdNav++'s test offset; the planner's settings were chosen on seed 1), --chunk at
a time in one jitted program, CrowdNav++'s and ICP's measures. `crowds`: the task's own humans
as files to train a planner's predictor on (`simulate.crowdnav.crowds`).
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.progress import Progress
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav import navigation, records
from gst_jax.simulate.crowdnav.crowds import write_crowds
from gst_jax.simulate.crowdnav.planner import SamplingMPC


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.navigate", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    evaluate_parser = commands.add_parser("evaluate", help="a planner over test episodes")
    add = evaluate_parser.add_argument
    add("--planner", choices=tuple(navigation.PLANNERS), default="mpc", help="mpc: GST's "
        "predictions; cv-mpc: constant velocity; standing-mpc: people standing; truth-mpc: the "
        "simulator's (default: mpc)")
    cli.add_prediction_flags(evaluate_parser)
    cli.add_humans_flags(evaluate_parser)
    add("--episodes", type=cli.positive_int, default=500, help="episodes (default: 500)")
    add("--plans", type=cli.at_least(SamplingMPC.fixed_plans, "the planner's fixed plans"),
        default=256, help="plans scored per step (default: 256)")
    add("--seed", type=int, default=1000, help="seed of the episodes (default: 1000)")
    add("--gif", type=cli.count, default=0, metavar="COUNT", help="GIFs of the first episodes")
    add("--chunk", type=cli.positive_int, default=navigation.CHUNK, help="episodes per "
        "compiled program (0.27 MB each with GST; %(default)s)")
    add("--overwrite", action="store_true", help="replace a record of the same run")
    cli.add_output_flags(evaluate_parser, workdir_help="output directory (default: "
                         "runs/navigate)", workdir_default="runs/navigate", compilation_cache=True)
    crowds = commands.add_parser("crowds", help="the task's humans as training files")
    cli.add_humans_flags(crowds, mix=True)
    crowds.add_argument("--episodes", type=cli.positive_int, default=2, help="per condition")
    crowds.add_argument("--seed", type=int, default=0, help="condition i plays seed + i (0)")
    cli.add_output_flags(crowds, workdir_help="output folder", workdir_default="runs/crowds")
    cli.run(navigate, parser, argv)


def navigate(args) -> None:
    if args.command == "crowds":
        written = write_crowds(Path(args.workdir), cli.crowd_conditions(args), args.episodes,
                               args.seed, Progress())
        return print(json.dumps(list(map(str, written))) if args.json else
                     f"written: {len(written)} files in {args.workdir}")
    described = navigation.described_run(args.planner, args.regions, args.alpha, args.humans,
                                         args.reactive, args.num_humans, args.shift, args.model,
                                         args.adapt, args.fresh_tracks)
    gst = load_model(args.model) if args.planner == "mpc" else None
    out = Path(args.workdir)
    result = navigation.evaluate_described(described, gst, args.plans, args.episodes, args.seed,
                                           out, args.gif, overwrite=args.overwrite,
                                           chunk=args.chunk, progress=Progress())
    print(json.dumps(result, indent=2) if args.json else records.summary(result, out))


if __name__ == "__main__":
    main()
