"""`python -m gst_jax.data stats`: window and pedestrian counts of the bundled datasets."""

from __future__ import annotations

import json

from gst_jax import cli
from gst_jax.config import ETH_UCY_SCENES, SCENES, DataConfig
from gst_jax.data.stats import format_stats, split_stats


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.data", __doc__)
    commands = parser.add_subparsers(dest="command", required=True)
    stats = commands.add_parser("stats", help="windows, pedestrians and fully detected counts")
    stats.add_argument("--scene", action="append", choices=SCENES,
                       help="scene to count (repeatable; default: the five ETH/UCY scenes)")
    cli.add_field_flag(stats, "--protocol", DataConfig, "protocol", default="paper")
    cli.add_grid_flags(stats)
    cli.add_field_flag(stats, "--data-dir", DataConfig, "data_dir", default=None)
    cli.add_own_data_flags(stats)
    stats.add_argument("--json", action="store_true",
                       help="print JSON in the schema of reference_windows.json")
    cli.run(show_stats, parser, argv)


def show_stats(args) -> None:
    args.scene, scenes = None, args.scene      # --scene is repeatable here: a list
    config = cli.data_config(args, DataConfig(protocol=args.protocol))
    result = split_stats(config, [config.scene] if config.data else
                         scenes or list(ETH_UCY_SCENES), cli.time_grid(args))
    print(json.dumps(result, indent=1) if args.json else format_stats(result))


if __name__ == "__main__":
    main()
