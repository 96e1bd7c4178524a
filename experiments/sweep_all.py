"""The comparative study across datasets (paper Figs. 4-6): one vmapped sweep per scene.

    python experiments/sweep_all.py --scenes zara1 hotel --epochs 20 --seeds 3 \
        --workdir runs/sweep_all

Each scene's sweep goes to <workdir>/<scene>/ (resumable, its own table and figure); the
cross-dataset figures and one markdown summary go to <workdir>/. --epochs is the budget:
tau anneals 0.5 -> 0.03 over it, so a short budget is a short training, not a truncated
200-epoch one; the learning rate decays every 50 epochs as in the release (`--schedule paper`)
or every epochs/4 (`--schedule compressed`, results/schedules.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from _figures import best_n_per_dataset, partial_vs_full_detection, sparse_gain_against_density

from gst_jax import cli
from gst_jax.config import (CROWD_SCENES, DETECTION, SCHEDULES, DataConfig, ModelConfig,
                            TrainConfig)
from gst_jax.training.members import plan_members, sweep_model_config
from gst_jax.training.sweep import fit_sweep, format_markdown


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(CROWD_SCENES), choices=CROWD_SCENES,
                        help="datasets to sweep (default: all seven)")
    parser.add_argument("--protocol", default="paper", help="split protocol (default: paper)")
    parser.add_argument("--edge-heads", default="0,1,2,4,8,16", type=cli.parse_edge_heads,
                        help="n to sweep, 0 = full")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per configuration (default: 3)")
    parser.add_argument("--seed", type=int, default=1000, help="first seed (default: 1000)")
    parser.add_argument("--fully-detected-only", default="both", choices=tuple(DETECTION),
                        help="detection modes to compare (default: both)")
    parser.add_argument("--epochs", type=int, default=200, help="epochs per sweep (budget)")
    parser.add_argument("--schedule", default=TrainConfig.schedule, choices=SCHEDULES,
                        help="learning-rate decay: paper (every 50 epochs) or compressed "
                             f"(every epochs/4) (default: {TrainConfig.schedule})")
    parser.add_argument("--eval-samples", type=int, default=20, help="K per member (default: 20)")
    parser.add_argument("--max-train-windows", type=int, default=0, help="smoke tests only")
    parser.add_argument("--max-eval-windows", type=int, default=0, help="smoke tests only")
    parser.add_argument("--workdir", default="runs/sweep_all", help="output directory")
    args = parser.parse_args()

    out = Path(args.workdir)
    members = plan_members(args.edge_heads, args.fully_detected_only,
                           [args.seed + i for i in range(args.seeds)])
    config = sweep_model_config(ModelConfig(), members)
    train_config = TrainConfig(epochs=args.epochs, seed=args.seed, schedule=args.schedule,
                               max_train_windows=args.max_train_windows)
    all_results = []
    for scene in args.scenes:
        print(f"== {scene}")
        data_config = DataConfig(scene=scene, protocol=args.protocol)
        all_results.append(fit_sweep(config, data_config, train_config, members, out / scene,
                                     eval_samples=args.eval_samples,
                                     max_eval_windows=args.max_eval_windows))

    partial_vs_full_detection(all_results, out / "partial_vs_full.png")
    sparse_gain_against_density(all_results, out / "sparse_gain_vs_density.png")
    best_n_per_dataset(all_results, out / "best_n.png")
    (out / "results.json").write_text(json.dumps(all_results, indent=2) + "\n")
    (out / "results.md").write_text("\n".join(format_markdown(r) for r in all_results))
    print((out / "results.md").read_text())
    print(f"written under {out}: results.json, results.md, partial_vs_full.png, "
          "sparse_gain_vs_density.png, best_n.png")


if __name__ == "__main__":
    main()
