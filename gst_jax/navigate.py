"""Robot navigation in CrowdNav++'s task with GST in the loop: `python -m gst_jax.navigate`.

    python -m gst_jax.navigate evaluate --planner mpc --episodes 500 --gif 3
    python -m gst_jax.navigate crowds --episodes 2 --seed 0 --workdir runs/crowds/train

A planner in `gst_jax.simulate.crowdnav.environment.CrowdNav` (CrowdNav++'s default task, or humans
who see the robot, more or fewer, or changing midway) over many episodes, --chunk at a time
in one jitted program; CrowdNav++'s and ICP's measures as a table. Episodes are seeded from
1000 (CrowdNav++'s test offset); the planner's settings were chosen on seed 1. `crowds` writes the task's own humans as
training data for a planner's predictor (`gst_jax.simulate.crowdnav.crowds`), from seeds
the study does not play.
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.progress import Progress
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.crowds import MIX, write_crowds
from gst_jax.simulate.crowdnav.environment import NO_SHIFT, POLICY_SHIFT, SPEED_SHIFT, EnvParams
from gst_jax.simulate.crowdnav.navigation import (CHUNK, PLANNERS, described_run, environment_for,
                                                  evaluate, summary)
from gst_jax.simulate.crowdnav.planner import SamplingMPC


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.navigate", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    evaluate_parser = commands.add_parser(
        "evaluate", help="run a planner over test episodes; CrowdNav++'s measures")
    add = evaluate_parser.add_argument
    add("--planner", choices=tuple(PLANNERS), default="mpc", help="mpc: against GST's "
        "predictions; cv-mpc: constant-velocity ones; standing-mpc: people standing where "
        "they are; truth-mpc: the simulator's own next positions (default: mpc)")
    add("--model", default="pretrained:crowdnav_sj_rand", type=cli.model_spec, help="mpc's "
        "predictor: a work directory or pretrained:NAME (default: %(default)s)")
    add("--regions", choices=("dtaci", "aci", "none"), default="dtaci", help="conformal "
        "regions around the predictions (default: dtaci)")
    add("--alpha", type=cli.open_fraction, default=0.1, help="their miscoverage (default 0.1)")
    add("--humans", choices=("orca", "social-force"), default="orca", help="how the humans "
        "walk: CrowdNav++'s ORCA (default) or its social force")
    add("--reactive", action="store_true", help="the humans see the robot (robot.visible)")
    add("--num-humans", type=cli.positive_int, default=20, help="humans (default: 20)")
    add("--shift", choices=(NO_SHIFT, SPEED_SHIFT, POLICY_SHIFT), default=NO_SHIFT, help=f"from "
        f"{EnvParams.shift_at_s:g} s on, humans {EnvParams.speed_factor:g}x faster (speed) or "
        "ORCA ones by social force (policy) (default: none)")
    add("--episodes", type=cli.positive_int, default=500, help="episodes (default: 500)")
    add("--plans", type=cli.at_least(SamplingMPC.fixed_plans, "the planner's fixed plans"),
        default=256, help="plans scored per step (default: 256)")
    add("--seed", type=int, default=1000, help="seed of the episodes (default: 1000)")
    add("--gif", type=cli.count, default=0, metavar="COUNT", help="GIFs of the first episodes")
    add("--chunk", type=cli.positive_int, default=CHUNK, help="episodes per compiled program, "
        "about 0.27 MB of memory each with GST (default: %(default)s)")
    add("--overwrite", action="store_true", help="replace a record of the same run")
    cli.add_output_flags(evaluate_parser, workdir_help="output directory (default: "
                         "runs/navigate)", workdir_default="runs/navigate", compilation_cache=True)
    crowds_parser = commands.add_parser(
        "crowds", help="write the task's humans as `frame ped x y` files to train on")
    crowds_parser.add_argument(
        "--episodes", type=cli.positive_int, default=2, help=f"episodes of each of the "
        f"{len(MIX)} conditions (ORCA and social force, with their shifts, reactive or not, 10, "
        "20 and 35 humans) (default: 2)")
    crowds_parser.add_argument("--seed", type=int, default=0, help="condition i plays from "
                               "seed + i; the study plays seed 1000 (default: 0)")
    cli.add_output_flags(crowds_parser, workdir_help="output directory (default: runs/crowds)",
                         workdir_default="runs/crowds")
    cli.run(navigate, parser, argv)


def navigate(args) -> None:
    if args.command == "crowds":
        written = write_crowds(Path(args.workdir), MIX, args.episodes, args.seed, Progress())
        print(json.dumps([str(p) for p in written]) if args.json else
              f"written: {len(written)} files in {args.workdir}")
        return
    described = described_run(args.planner, args.regions, args.alpha, args.humans,
                              args.reactive, args.num_humans, args.shift, args.model)
    gst = load_model(args.model) if args.planner == "mpc" else None
    env, params = environment_for(described, gst)
    planner = SamplingMPC(num_plans=args.plans, horizon=env.pred_len, step_s=params.step_s)
    result = evaluate(env, params, planner, args.episodes, args.seed, Path(args.workdir), described,
                      args.gif, overwrite=args.overwrite, chunk=args.chunk, progress=Progress())
    print(json.dumps(result, indent=2) if args.json else summary(result))


if __name__ == "__main__":
    main()
