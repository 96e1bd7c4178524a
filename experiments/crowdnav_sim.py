"""A planner's predictor trained here, beside CrowdNav++'s own, on simulated crowds:

    python -m gst_jax.train --data runs/sim_crowds --fps 4 --step 0.25 --obs-len 5 \\
        --pred-len 5 --edge-heads 0 --no-ghost --node-dim 64 --encoder-layers 1 --lstm-dim 64 \\
        --temporal faster_lstm --output gaussian --epochs 100 --workdir runs/crowdnav_sim
    python experiments/crowdnav_sim.py --model runs/crowdnav_sim --data runs/sim_crowds
    python experiments/crowdnav_sim.py --data runs/sim_crowds --publish   # results/crowdnav_sim.md

runs/sim_crowds held 40 episodes of a numpy stand-in simulator of ORCA-like humans, since
removed (issue 90: one simulator of humans, the navigation task's; `python -m gst_jax.navigate
crowds` writes its crowds): `pretrained:crowdnav_sim` and results/crowdnav_sim.md were made
on them. The script reads any folder of 0.25 s crowds (e.g. `navigate crowds`' files), but
those episodes can no longer be made.

Both models on the test split of the simulated crowds (the last 20 % of every episode):
the paper's protocol (20 sampled runs; GST (P) samples its Gaussians) and the mean mode a
planner calls (CrowdNav++'s `sampling=False`: one run, every step the Gaussian's mean), with
constant velocity on the same pedestrians. CrowdNav++'s is its public `..._seed1000/sj`
checkpoint (weights read from tests/fixtures/crowdnav_parity.npz), trained on CrowdNav++'s
own simulator. Writes crowdnav_sim.md and .json into runs/crowdnav_sim_table/ (or --workdir;
not runs/crowdnav_sim, the work directory of the training above); `--publish` replaces the
published ones in the checkout's results/.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import numpy as np

from _common import add_results_flags, results_folder
from gst_jax import crowdnav, data
from gst_jax.config import DataConfig
from gst_jax.evaluation import evaluate_params
from gst_jax.predict import make_predict
from gst_jax.runs import load_model

FIXTURE = Path(__file__).parents[1] / "tests" / "fixtures" / "crowdnav_parity.npz"


def crowdnav_checkpoint() -> crowdnav.Predictor:
    fixture = np.load(FIXTURE)
    prefix = "seed1000/state_dict/"
    state_dict = {k[len(prefix):]: fixture[k] for k in fixture.files if k.startswith(prefix)}
    return crowdnav.from_state_dict(state_dict, json.loads(str(fixture["seed1000/args"])))


def scores(params, config, test_set) -> dict:
    """The paper's protocol (20 samples) and the mean mode (one run of means)."""
    sampled = evaluate_params(params, jax.random.key(0), test_set, config, num_samples=20,
                              with_kde=False)
    mean = evaluate_params(params, jax.random.key(0), test_set, config, num_samples=1,
                           with_kde=False, predict=make_predict(config, 1, with_graph=False,
                                                                mean=True))
    return {"aoe": sampled["aoe"], "foe": sampled["foe"], "min_ade": sampled["min_ade"],
            "min_fde": sampled["min_fde"], "mean_aoe": mean["aoe"], "mean_foe": mean["foe"],
            "cv_aoe": sampled["cv_aoe"], "cv_foe": sampled["cv_foe"],
            "pedestrians": sampled["pedestrians"]}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="pretrained:crowdnav_sim",
                        help="the model trained here (default: pretrained:crowdnav_sim)")
    parser.add_argument("--data", type=Path, required=True, help="the simulated crowds")
    add_results_flags(parser, "crowdnav_sim_table", "crowdnav_sim.md and .json", runs=False)
    args = parser.parse_args(argv)
    out = results_folder(args)
    ours = load_model(args.model)
    theirs = crowdnav_checkpoint()
    data_config = DataConfig(scene=args.data.name, data=str(args.data.absolute()), fps=4)
    test_set = data.load_split(data_config, "test", ours.model_config.grid)
    start = time.perf_counter()
    rows = {"gst_jax (trained here)": scores(ours.params, ours.model_config, test_set),
            "CrowdNav++ seed1000/sj": scores(theirs.params, theirs.config, test_set)}
    seconds = time.perf_counter() - start
    lines = ["# A planner's predictor on simulated crowds", "",
             f"Test split of `{args.data.name}` ({len(test_set)} windows of 5 observed and 5 "
             "predicted steps of 0.25 s, the last 20 % of each of its episodes); AOE / FOE in "
             "metres on fully detected pedestrians. Sampled: mean over 20 runs (hard graphs at "
             "tau 0.03, Gaussians sampled); mean mode: one run of each step's mean, as "
             "CrowdNav++ calls its predictor. CV: constant velocity on the same pedestrians. "
             f"Ours: `{ours.name}`, epoch {ours.epoch}. Written by "
             "`python experiments/crowdnav_sim.py` in "
             f"{seconds:.0f} s.", "",
             "| model | sampled AOE / FOE | best of 20 | mean mode AOE / FOE | CV |",
             "|---|---|---|---|---|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['aoe']:.3f} / {r['foe']:.3f} | {r['min_ade']:.3f} / "
                     f"{r['min_fde']:.3f} | {r['mean_aoe']:.3f} / {r['mean_foe']:.3f} | "
                     f"{r['cv_aoe']:.3f} / {r['cv_foe']:.3f} |")
    out.mkdir(parents=True, exist_ok=True)
    (out / "crowdnav_sim.md").write_text("\n".join(lines) + "\n")
    (out / "crowdnav_sim.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(json.dumps(rows, indent=2) if args.json else "\n".join(lines))


if __name__ == "__main__":
    main()
