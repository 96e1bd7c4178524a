"""Ablation sweeps over n, detection and seeds as one program (paper Figs. 4-6).

    python -m gst_jax.sweep --scene zara1 --edge-heads 0,1,2,4,8,16 --seeds 3 \\
        --fully-detected-only both

Every (n, detection, seed) member is trained by one training step over the members (looped
inside the program on a CPU, vmapped on a GPU) on the same batches, then evaluated on the
test split; the work directory gets results.json, .csv,
.md and aoe_foe_vs_n.png. Rerunning the command resumes the sweep.
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.io.workdir import RUNS, sweep_name
from gst_jax.training.members import plan_members, sweep_model_config
from gst_jax.training.sweep import fit_sweep, format_markdown


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.sweep", __doc__)
    cli.add_data_flags(parser)
    cli.add_model_flags(parser, several_edge_heads=True)
    cli.add_train_flags(parser, sweep=True)
    cli.add_device_flags(parser)
    parser.add_argument("--eval-samples", type=cli.positive_int, default=20,
                        help="K samples (runs) per member in the evaluation (default: 20)")
    parser.add_argument("--max-eval-windows", type=cli.count, default=0,
                        help="evaluate on the first k test windows only (smoke tests; "
                             "default: all)")
    cli.add_output_flags(parser, workdir_help="where checkpoints, metrics.jsonl, results and "
                         "figures go; rerunning resumes (default: runs/sweep-<scene>-e<epochs>)")
    cli.run(sweep, parser, argv)


def sweep(args) -> None:
    members = plan_members(args.edge_heads, args.fully_detected_only,
                           [args.seed + i for i in range(args.seeds)])
    config = sweep_model_config(cli.model_config(args), members)
    data_config, train_config = cli.data_config(args), cli.train_config(args)
    workdir = Path(args.workdir or RUNS / sweep_name(data_config, train_config))
    cli.say(f"work directory: {workdir}; {len(members)} members, head slots {config.head_slots}")
    results = fit_sweep(config, data_config, train_config, members, workdir,
                        eval_samples=args.eval_samples, max_eval_windows=args.max_eval_windows,
                        devices=cli.devices(args, members=len(members)))
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print(format_markdown(results))
        cli.say(f"written: {workdir}/results.json, .csv, .md, aoe_foe_vs_n.png")


if __name__ == "__main__":
    main()
