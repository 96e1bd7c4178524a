"""Shipped models: `python -m gst_jax.pretrained list`, `... export RUN --name NAME`."""

from __future__ import annotations

import json

from gst_jax import cli, pretrained
from gst_jax.config import DataConfig
from gst_jax.data import data_name


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.pretrained", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    export = commands.add_parser("export", help="copy a trained run into gst_jax/pretrained/<name>")
    export.add_argument("run", help="work directory of `python -m gst_jax.train`")
    export.add_argument("--name", required=True, help="e.g. eth_d")
    export.add_argument("--check-data", default=None, metavar="PATH",
                        help="data of the fixed-key check where the run's is not bundled: a path "
                             "into the bundled data (e.g. samples/sim_crowds)")
    export.add_argument("--check-fps", type=cli.positive_float, default=None,
                        help="frame ids per second of --check-data")
    listing = commands.add_parser("list", help="shipped models and their measured test AOE/FOE")
    listing.add_argument("--json", action="store_true", help="print every model's meta.json")
    cli.run(command, parser, argv)


def command(args) -> None:
    if args.command == "export":
        from gst_jax.pretrained.export import export   # evaluation code, only when exporting
        check = args.check_data and DataConfig(scene=data_name(args.check_data),
                                               data=args.check_data, fps=args.check_fps)
        print(f"written: {export(args.run, args.name, check or None)}")
        return
    metas = {name: pretrained.load_meta(name) for name in pretrained.available()}
    if args.json:
        print(json.dumps(metas, indent=2))
        return
    for name, meta in metas.items():
        m = meta.get("test_metrics") or {}
        print(f"{name}: epoch {meta['epoch']}, AOE {m.get('aoe', float('nan')):.3f} "
              f"FOE {m.get('foe', float('nan')):.3f} ({m.get('protocol', 'not evaluated')})")
        if per_scene := meta.get("test_metrics_per_scene"):      # the general model
            print("  per scene AOE / FOE: " + ", ".join(
                f"{scene} {m['aoe']:.3f} / {m['foe']:.3f}" for scene, m in per_scene.items()))


if __name__ == "__main__":
    main()
