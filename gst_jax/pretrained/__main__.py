"""`python -m gst_jax.pretrained export RUN --name NAME` / `python -m gst_jax.pretrained list`."""

import argparse

from gst_jax import pretrained

parser = argparse.ArgumentParser(prog="python -m gst_jax.pretrained", description=__doc__)
commands = parser.add_subparsers(dest="command", required=True)
export = commands.add_parser("export", help="copy a trained run into gst_jax/pretrained/<name>")
export.add_argument("run", help="work directory of `python -m gst_jax.train`")
export.add_argument("--name", required=True, help="e.g. eth_d")
commands.add_parser("list", help="shipped models and their measured test AOE/FOE")
args = parser.parse_args()
if args.command == "export":
    print(f"written: {pretrained.export(args.run, args.name)}")
else:
    for name in pretrained.available():
        meta = pretrained.load_meta(name)
        m = meta.get("test_metrics") or {}
        print(f"{name}: epoch {meta['epoch']}, AOE {m.get('aoe', float('nan')):.3f} "
              f"FOE {m.get('foe', float('nan')):.3f} ({m.get('protocol', 'not evaluated')})")
