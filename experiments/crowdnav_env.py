"""A planner's predictor trained on the navigation task's own humans, against constant velocity,
open loop, on held-out episodes of each condition (issue 90, part 2):

    python -m gst_jax.navigate crowds --episodes 3 --seed 0 --workdir runs/crowds/train
    python -m gst_jax.navigate crowds --episodes 1 --seed 100 --workdir runs/crowds/test
    python -m gst_jax.train --data runs/crowds/train --fps 4 --step 0.25 --obs-len 5 \\
        --pred-len 5 --edge-heads 0 --no-ghost --node-dim 64 --encoder-layers 1 --lstm-dim 64 \\
        --temporal faster_lstm --output gaussian --schedule compressed --epochs 40 \\
        --seed 1000 --workdir runs/crowdnav_env
    python -m gst_jax.train ...the same flags... --score-partial --hide-history 0.3 \
        --workdir runs/env_partial_a                      # pretrained:crowdnav_env_partial
    python -m gst_jax.train ...the same flags... --score-partial --hide-history 0.3 \
        --obs-len 8 --workdir runs/env_partial_obs8       # pretrained:crowdnav_env_obs8
    python experiments/crowdnav_env.py --model runs/crowdnav_env --publish

The held-out episodes (seeds 100-129, one per condition of the training mix; the training's
are seeds 0-29, the navigation study's 1000 on) are grouped by how their humans walk: ORCA
and social force without a shift, and the two shifts after they began (windows whose
predicted steps all lie after 6 s). Each model predicts as a planner calls it (the mean of
its Gaussians, one run) and with the paper's protocol (20 sampled runs); constant velocity
on the same pedestrians. Writes crowdnav_env.md and .json into runs/crowdnav_env_table/ (or
--workdir); --publish replaces results/crowdnav_env.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax

from _common import add_results_flags, results_folder
from gst_jax.config import DataConfig
from gst_jax.data import WindowSet, load_split
from gst_jax.evaluation import evaluate_params
from gst_jax.predict import make_predict
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import EnvParams

# The models compared: the one trained here on the task's humans (and again, scoring the
# partially detected too, and so with 8 observed steps), CrowdNav++'s (which the navigation
# study plans with) and the one trained on the former numpy stand-in crowds.
MODELS = ("pretrained:crowdnav_env_partial", "pretrained:crowdnav_env_obs8",
          "pretrained:crowdnav_sj_rand",
          "pretrained:crowdnav_sim")
# The first step a shift moves (the humans' velocities from the state at 6 s on).
SHIFTED_FROM = round(EnvParams.shift_at_s / EnvParams.step_s) + 1
# Condition groups: (name, which files, whether only windows predicted after the shift).
GROUPS = (("ORCA", lambda name: name.startswith("orca") and "shift" not in name, False),
          ("social force", lambda name: name.startswith("social_force") and "shift" not in name,
           False),
          ("1.5x faster, after 6 s", lambda name: "shiftspeed" in name, True),
          ("ORCA to social force, after 6 s", lambda name: "shiftpolicy" in name, True))


def group_windows(folder: Path, grid) -> dict[str, WindowSet]:
    """Each group's windows of the held-out files in `folder`, on the model's grid."""
    groups = {}
    for name, chosen, after_shift in GROUPS:
        windows = []
        for path in sorted(p for p in folder.glob("*.txt") if chosen(p.name)):
            config = DataConfig(scene=path.stem, data=str(path.absolute()), fps=1 / grid.step_s)
            for window in load_split(config, "all", grid).windows:
                first_predicted = window.start_frame + grid.obs_len * window.frame_step
                if not after_shift or first_predicted >= SHIFTED_FROM:
                    windows.append(window)
        groups[name] = WindowSet(tuple(windows), name)
    return groups


def scores(run, windows: WindowSet) -> dict:
    """The mean mode a planner calls, and the paper's 20 sampled runs; CV beside them."""
    config = run.model_config
    mean = evaluate_params(run.params, jax.random.key(0), windows, config, num_samples=1,
                           with_kde=False, predict=make_predict(config, 1, with_graph=False,
                                                                mean=True))
    sampled = evaluate_params(run.params, jax.random.key(0), windows, config, num_samples=20,
                              with_kde=False)
    return {"pedestrians": mean["pedestrians"], "mean_aoe": mean["aoe"], "mean_foe": mean["foe"],
            "aoe": sampled["aoe"], "foe": sampled["foe"], "cv_aoe": mean["cv_aoe"],
            "cv_foe": mean["cv_foe"]}


def table(rows: list[dict]) -> str:
    lines = ["| humans | windows | pedestrians | model | ADE, mean mode | FDE, mean mode | AOE, "
             "20 samples | FOE, 20 samples | constant velocity ADE / FDE |", "|---" * 9 + "|"]
    for row in rows:
        lines.append(f"| {row['group']} | {row['windows']} | {row['pedestrians']} | "
                     f"{row['model']} | {row['mean_aoe']:.3f} | {row['mean_foe']:.3f} | "
                     f"{row['aoe']:.3f} | {row['foe']:.3f} | {row['cv_aoe']:.3f} / "
                     f"{row['cv_foe']:.3f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="pretrained:crowdnav_env",
                        help="the model trained on the task's humans (default: %(default)s)")
    parser.add_argument("--test-data", type=Path, default=Path("runs/crowds/test"),
                        help="the held-out episodes (default: %(default)s)")
    add_results_flags(parser, "crowdnav_env_table", "crowdnav_env.md and .json", runs=False)
    args = parser.parse_args(argv)
    rows = []
    for spec in (args.model, *MODELS):
        run = load_model(spec)
        for group, windows in group_windows(args.test_data, run.model_config.grid).items():
            started = time.perf_counter()
            rows.append({"group": group, "model": spec.removeprefix("pretrained:"),
                         "windows": len(windows), **scores(run, windows),
                         "seconds": round(time.perf_counter() - started, 1)})
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    rows.sort(key=lambda row: [g[0] for g in GROUPS].index(row["group"]))
    text = "\n".join([
        "# A planner's predictor trained on the navigation task's own humans", "",
        "Made by `python experiments/crowdnav_env.py --publish` (commands in its docstring): "
        "held-out episodes of the task's humans (one per condition of the training mix, seeds "
        "100-129), open loop; each model as a planner calls it (the mean of its Gaussians) and "
        "with the paper's protocol (20 samples), constant velocity on the same pedestrians; "
        "metres.", "", table(rows), ""])
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    (out / "crowdnav_env.md").write_text(text)
    (out / "crowdnav_env.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
