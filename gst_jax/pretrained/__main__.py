"""Shipped models: `python -m gst_jax.pretrained list`, `... choose --data FILE` (rank them on
your data's validation windows beside constant velocity), `... export MODEL --name NAME` (ship
it), `... export MODEL --out DIR` (DIR/model.safetensors + config.json, read by load_model)."""

from __future__ import annotations

import json
import shlex
import sys

from gst_jax import cli, pretrained
from gst_jax.config import DataConfig
from gst_jax.data import data_name


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.pretrained", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    export = commands.add_parser("export", help="a model as safetensors + config.json: into "
                                 "gst_jax/pretrained/<name> (--name) or a folder (--out)")
    export.add_argument("run", help="a work directory, SWEEP_DIR:MEMBER, pretrained:NAME, a "
                        "weights folder, or a CrowdNav++ checkpoint folder (gst_updated/results/"
                        "<run>/sj, read without torch)")
    where = export.add_mutually_exclusive_group(required=True)
    where.add_argument("--name", help="ship it as gst_jax/pretrained/NAME, e.g. eth_d")
    where.add_argument("--out", metavar="DIR", help="write DIR/model.safetensors, DIR/config.json")
    export.add_argument("--format", choices=["safetensors"], default="safetensors",
                        help="the weights format (safetensors, the only one written)")
    export.add_argument("--check-data", default=None, metavar="PATH",
                        help="with --name, data of the fixed-key check where the run's is not "
                             "bundled: a path into the bundled data (e.g. samples/crowdnav_orca)")
    export.add_argument("--check-fps", type=cli.field_type(DataConfig, "fps"), default=None,
                        help="frame ids per second of --check-data")
    export.add_argument("--source", help="where the parameters came from (default: the model)")
    export.add_argument("--licence", help="their licence and attribution, one line")
    export.add_argument("--licence-file", action="append", default=[], metavar="FILE",
                        help="copied beside the weights (a LICENSE as LICENSE.<its folder>)")
    listing = commands.add_parser("list", help="shipped models: their measured test AOE/FOE, "
                                  "time step and speed range")
    listing.add_argument("--json", action="store_true", help="print every model's meta.json")
    cli.add_choice_flags(commands.add_parser("choose", help="rank the shipped models whose time "
                         "step fits your data, and constant velocity, on its validation windows"))
    argv = sys.argv[1:] if argv is None else argv
    command_line = shlex.join(["python", "-m", "gst_jax.pretrained", *argv])
    cli.run(lambda args: command(args, command_line), parser, argv)


def command(args, command_line: str) -> None:
    if args.command == "export":
        from gst_jax.pretrained import export  # evaluation code, only when exporting
        given = dict(source=args.source, licence=args.licence, licence_files=args.licence_file,
                     command=command_line)
        check = args.check_data and DataConfig(scene=data_name(args.check_data),
                                               data=args.check_data, fps=args.check_fps)
        print("written:", export.export_weights(args.run, args.out, **given) if args.out
              else export.export(args.run, args.name, check or None, **given))
        return
    if args.command == "choose":
        from gst_jax.pretrained import choose  # evaluation code, only when choosing
        print(choose.report(cli.data_config(args), args.models, num_samples=args.samples,
                            seed=args.seed, as_json=args.json))
    elif args.json:
        print(json.dumps({name: pretrained.load_meta(name) for name in pretrained.available()},
                         indent=2))
    else:
        for name in pretrained.available():
            print("\n".join(pretrained.describe(name)))

if __name__ == "__main__":
    main()
