"""Simulate the paper's robot/human scenarios with trained models: `python -m gst_jax.simulate`.

    python -m gst_jax.simulate pretrained:eth runs/sweep-hotel-e10:n4-partial-seed1000
    python -m gst_jax.simulate pretrained:crowd_d --encounters 1000 --humans orca

Every detected agent, the robot included, moves by the model's first predicted displacement
(--humans orca: the people by ORCA); the table gives the robot's minimum distance,
collisions, progress, path-length ratio and whether it froze or turned back. One PNG (and,
with --animate, a GIF) per run; --encounters: rates with 95 % intervals, encounters.png.
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.runs import load_model
from gst_jax.simulate.paper import study
from gst_jax.simulate.paper.encounters import format_encounters
from gst_jax.simulate.paper.loop import MODEL_HUMANS, ORCA_HUMANS
from gst_jax.simulate.paper.scenarios import SCENARIOS


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.simulate", __doc__)
    parser.add_argument("runs", nargs="*", help="work directories, SWEEP_DIR:MEMBER (e.g. "
                        "runs/sweep-hotel-e10:n4-partial-seed1000) or pretrained:NAME (e.g. "
                        "pretrained:eth_d); none = only the constant-velocity model")
    parser.add_argument("--scenario", default="all", choices=("all", *SCENARIOS),
                        help="a: late crossing, b: boundary wanderers, c: intersection, "
                             "d: oncoming group (default: all)")
    parser.add_argument("--edge-heads", default=None, type=cli.parse_edge_heads,
                        help="comma-separated n to run each model with (default: its own)")
    parser.add_argument("--encounters", type=cli.positive_int, default=None, metavar="COUNT",
                        help="instead, COUNT random encounters (gst_jax/simulate/paper/"
                             "encounters.py), one program per model: rates with 95%% intervals")
    parser.add_argument("--humans", choices=(MODEL_HUMANS, ORCA_HUMANS), default=MODEL_HUMANS,
                        help="how the people move: model, by its prediction, as the robot "
                        "(the paper's); orca, by ORCA along their lines, giving way to the "
                        "robot (CrowdNav++'s reactive humans) (default: model)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the samples and encounters")
    parser.add_argument("--animate", action="store_true", help="also a GIF of every run")
    cli.add_output_flags(parser, workdir_help="output directory (default: runs/simulate)",
                         workdir_default="runs/simulate")
    cli.run(simulate, parser, argv)


def simulate(args) -> None:
    runs = [load_model(spec) for spec in args.runs]
    models, out = study.step_models(runs, args.edge_heads), Path(args.workdir)
    settings = dict(grid=study.time_grid(runs), seed=args.seed, humans=args.humans)
    rows: dict | list[dict]                 # the encounter study's, or a row per scenario run
    if args.encounters:
        rows, _ = study.run_encounter_study(models, args.encounters, out, **settings)
        table, written = format_encounters(rows), "encounters.json and encounters.png"
    else:
        names = list(SCENARIOS) if args.scenario == "all" else [args.scenario]
        rows = study.run_scenarios(models, names, out, animate=args.animate, **settings)
        table = study.format_markdown(rows)
        written = f"results.json and one {'PNG and GIF' if args.animate else 'PNG'} per run"
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print(table)
    cli.say(f"written: {out}/{written}")


if __name__ == "__main__":
    main()
