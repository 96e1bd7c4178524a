"""Does planning against GST's calibrated predictions help a robot in CrowdNav++'s task?
(issue 60): the sampling MPC against GST's predictions and against constant velocity, each
with DtACI discs and without, over the same 500 test episodes (seed 1000 on); and both with
DtACI discs among CrowdNav++'s social-force humans instead of its ORCA ones.

    python experiments/navigation.py                 # runs/navigation/
    python experiments/navigation.py --publish       # results/navigation.{md,json}

Each configuration is `python -m gst_jax.navigate evaluate --planner P --regions R
[--humans social-force] --episodes 500` (`gst_jax.simulate.navigation.evaluate`); one whose
record is already in the
output folder is not run again. Beside them, CrowdNav++'s own released test logs (its RL
policy with GST, 500 episodes each), whose setting differs (below the table).
"""

from __future__ import annotations

import argparse
import json
import math

from _common import add_results_flags, results_folder

from gst_jax.runs import load_model
from gst_jax.simulate.environment import CONSTANT_VELOCITY, CrowdNav
from gst_jax.simulate.navigation import evaluate, format_table, record_name, row_label
from gst_jax.simulate.planner import SamplingMPC
from gst_jax.stream import Regions

CONFIGURATIONS = [("mpc", "dtaci", "orca"), ("mpc", "none", "orca"), ("cv-mpc", "dtaci", "orca"),
                  ("cv-mpc", "none", "orca"), ("mpc", "dtaci", "social-force"),
                  ("cv-mpc", "dtaci", "social-force")]
MODEL = "pretrained:crowdnav_sj_rand"
# CrowdNav++'s released test logs (commit 3907731, trained_models/*/test/*.log, line 9; 500
# episodes each; path length over all episodes, navigation time over the successes).
CROWDNAV = [
    ("CrowdNav++ RL with GST (GST_predictor_rand, its log test_41665.pt.log)",
     {"success": 0.88, "collision": 0.12, "timeout": 0.00, "navigation_time_s": 14.14,
      "path_length_m": 20.08, "intrusion_ratio": 0.0835}),
    ("CrowdNav++ ORCA robot (its released log)",
     {"success": 0.69, "collision": 0.29, "timeout": 0.02, "intrusion_ratio": 0.1961}),
]


def run(planner: str, regions: str, humans: str, episodes: int, seed: int, out) -> dict:
    found = out / f"{record_name(planner, regions, humans, episodes, seed)}.json"
    if found.exists():
        return json.loads(found.read_text())
    discs = None if regions == "none" else Regions(regions, 0.1)
    predictor = load_model(MODEL) if planner == "mpc" else CONSTANT_VELOCITY
    env, params = CrowdNav.with_predictor(predictor, regions=discs,
                                          human_policy=humans.replace("-", "_"))
    mpc = SamplingMPC(horizon=env.pred_len, step_s=params.step_s)
    return evaluate(env, params, mpc, episodes, seed, out, {
        "planner": planner, "regions": regions, "alpha": 0.1, "humans": humans,
        "model": MODEL if planner == "mpc" else None})


def success_half_width(success: list[float], episodes: int) -> tuple[float, float]:
    """The mean success rate and its binomial 95 % half-width over `episodes`."""
    mean = sum(success) / len(success)
    return mean, 1.96 * math.sqrt(mean * (1 - mean) / episodes)


def reading(rows: list[dict], episodes: int) -> str:
    """What the rows (the four planners among ORCA humans) say about success and
    intrusion, with the binomial 95 % half-width."""
    success = [row["success"] for row in rows]
    mean, half = success_half_width(success, episodes)
    spread = max(success) - min(success)
    verdict = "within" if spread <= half else "beyond"
    with_discs = [row["intrusion_ratio"] for row in rows if row["regions"] != "none"]
    without = [row["intrusion_ratio"] for row in rows if row["regions"] == "none"]
    change = sum(with_discs) / sum(without) - 1
    time_with = [row["navigation_time_s"] for row in rows if row["regions"] != "none"]
    time_without = [row["navigation_time_s"] for row in rows if row["regions"] == "none"]
    slower = (sum(time_with) - sum(time_without)) / len(time_with)
    return (f"Over {episodes} episodes a success rate of {mean:.2f} has a 95 % half-width of "
            f"{half:.3f}; the four planners' success rates span {spread:.3f}, {verdict} it. "
            f"The DtACI discs change the intrusion ratio by {100 * change:+.0f} % and the "
            f"navigation time by {slower:+.1f} s (means over both predictors).")


def among_social_force(rows: list[dict], episodes: int) -> str:
    """GST against constant velocity among social-force humans, as `reading` does."""
    success = [row["success"] for row in rows]
    _, half = success_half_width(success, episodes)
    spread = max(success) - min(success)
    return (f"Among social-force humans the two planners' success rates ({min(success):.3f}, "
            f"{max(success):.3f}) span {spread:.3f}, {'within' if spread <= half else 'beyond'} "
            f"their half-width of {half:.3f}.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1000)
    add_results_flags(parser, "navigation", "the records and navigation.md", runs=False)
    args = parser.parse_args()
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    runs = out / "runs" / "navigation" if args.publish else out
    runs.mkdir(parents=True, exist_ok=True)
    rows = []
    for planner, regions, humans in CONFIGURATIONS:
        row = {**run(planner, regions, humans, args.episodes, args.seed, runs), "humans": humans}
        rows.append({**row, "label": row_label(row)})
    published = rows + [{"label": f"{name} | | | ORCA", **figures}
                        for name, figures in CROWDNAV]
    text = "\n".join([
        "# Planning against GST's calibrated predictions in CrowdNav++'s task", "",
        f"Made by `python experiments/navigation.py --publish`: {args.episodes} test episodes "
        f"(seed {args.seed} on, the same for every row) of `gst_jax.simulate.environment."
        "CrowdNav` (CrowdNav++'s default task: 20 ORCA humans who ignore the robot, 0.25 s "
        "steps, 50 s; in the rows marked so, its social-force humans instead), "
        "docs/navigation.md. Navigation time over the successful episodes, path "
        "length over all, intrusion ratio: the share of an episode's steps in which a human's "
        "next 5 positions come within 0.6 m of the robot; mean radius: of the discs the "
        "planner was given.", "", format_table(published), "",
        reading([row for row in rows if row["humans"] == "orca"], args.episodes) + " "
        + among_social_force([row for row in rows if row["humans"] != "orca"], args.episodes),
        "",
        "CrowdNav++'s rows are its released test logs (its RL policy with GST, trained over "
        "20 M steps; 500 episodes of its own simulator, whose rules this environment follows "
        "but for the four differences of docs/navigation.md), not runs here: other episodes. "
        "ICP (tedhuang96/icp, WAFR 2024) publishes no results in its repository and its "
        "paper's table could not be read here; its simulator differs (5-10 humans who react "
        "to the robot, radius 0.4 m).", ""])
    (out / "navigation.md").write_text(text)
    (out / "navigation.json").write_text(json.dumps(published, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
