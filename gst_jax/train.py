"""Train GST on one scene: `python -m gst_jax.train` (resumes where a run stopped).

With no arguments it trains the paper's configuration (GST (D), n = 1, ghost, seed 1000,
200 epochs, 16 scenes per step, Adam 1e-3 x 0.3 every 50 epochs, tau annealed 0.5 -> 0.03,
random rotation, dropout 0.1) on `eth` under the paper protocol. Every random draw is a
function of (seed, epoch, step) and checkpoints are taken at epoch boundaries, so a run
killed at any point and started again with the same command ends with exactly the
parameters of an uninterrupted run.
"""

from __future__ import annotations

import json
from pathlib import Path

from gst_jax import cli
from gst_jax.io.workdir import RUNS, run_name
from gst_jax.training.loop import fit


def main(argv: list[str] | None = None) -> None:
    parser = cli.parser("gst_jax.train", __doc__)
    cli.add_data_flags(parser, fine_tuning=True)
    cli.add_model_flags(parser)
    cli.add_train_flags(parser)
    cli.add_device_flags(parser)
    cli.add_output_flags(parser, workdir_help="where checkpoints, metrics.jsonl and summary.json "
                         "go; rerunning the same command resumes there "
                         "(default: runs/<scene>-<protocol>-<d|p>-n<n>-e<epochs>-seed<seed>)")
    cli.run(train, parser, argv)


def train(args) -> None:
    data_config, model_config, train_config = (cli.data_config(args), cli.model_config(args),
                                               cli.train_config(args))
    workdir = Path(args.workdir or RUNS / run_name(data_config, model_config, train_config))
    cli.say(f"work directory: {workdir}")
    summary = fit(model_config, data_config, train_config, workdir, devices=cli.devices(args))
    if args.json:
        print(json.dumps(summary, indent=2))
        return
    done = "already trained" if summary.get("already_finished") else "trained"
    print(f"{done} {summary['epochs']} epochs on {summary['train_windows']} windows in "
          f"{summary['wall_time_s']:.0f} s; final loss {summary['final_loss']:.4f}; "
          f"evaluate with: python -m gst_jax.evaluate {workdir}")
    if "fine_tuning" in summary:
        print(format_fine_tuning(summary["fine_tuning"]))


def format_fine_tuning(report: dict) -> str:
    """Which epoch a fine-tuning kept, and the test windows' AOE/FOE of it, of the model it
    started from and of constant velocity."""
    epoch, aoe = report["selected_epoch"], f"{report['val_aoe']:.3f} m"
    if epoch and "start_val_aoe" in report:     # else a selection made before it was kept
        aoe += f" against {report['start_val_aoe']:.3f} m for the starting model {report['from']}"
    kept = (f"epoch {epoch}" if epoch
            else f"the starting model ({report['from']}): no epoch improved")
    lines = [f"kept {kept} on validation AOE ({aoe}, {report['val_windows']} windows)"]
    if "test" in report:
        test = report["test"]
        lines.append(f"test split, {test['windows']} windows, 20 runs: AOE / FOE (m)")
        for name, key in ((f"fine-tuned (epoch {epoch})", "tuned"), (report["from"], "start"),
                          ("constant velocity", "constant_velocity")):
            lines.append(f"  {name:32s} {test[key]['aoe']:.3f} / {test[key]['foe']:.3f}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
