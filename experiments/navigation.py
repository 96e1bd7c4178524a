"""Does planning against GST's calibrated predictions help a robot in CrowdNav++'s task, and
when would any predictor? (issues 60 and 75): the sampling MPC against GST's predictions and
against constant velocity, each with DtACI discs and without, over the same 500 test episodes
(seed 1000 on); both with DtACI discs among CrowdNav++'s social-force humans; and (issue 75)
among humans who see the robot and give way to it (ORCA and social force, 10, 20 and 35 of
them) and humans who change midway (1.5x faster, or ORCA to social force, 6 s in), against
four predictors: none (people standing where they are), constant velocity, GST, and the
simulator's own next positions (truth: what no predictor can beat), each with and without
DtACI discs.

    python experiments/navigation.py                 # runs/navigation/
    python experiments/navigation.py --publish       # results/navigation.{md,json}
    python experiments/navigation.py --tabulate      # only the records already made

Each configuration is `python -m gst_jax.navigate evaluate --planner P --regions R
[--humans social-force] [--reactive] [--num-humans N] [--shift S] --episodes 500`
(`gst_jax.simulate.crowdnav.navigation.evaluate`); one whose record is already in the output
folder is not run again, so an interrupted study continues where it stopped. Beside them,
CrowdNav++'s own released test logs (its RL policy with GST, 500 episodes each), whose setting
differs (below the table).
"""

from __future__ import annotations

import argparse
import json
import math
import time

from _common import add_results_flags, results_folder
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import NO_SHIFT, POLICY_SHIFT, SPEED_SHIFT
from gst_jax.simulate.crowdnav.navigation import described_run, evaluate_described
from gst_jax.simulate.crowdnav.planner import SamplingMPC
from gst_jax.simulate.crowdnav.records import (
    compare,
    format_table,
    record_name,
    row_label,
    setting,
)

# A scenario, how the humans walk: (policy, reactive, num_humans, shift). Issue 60: CrowdNav++'s
# default humans (20 ORCA, ignoring the robot) and its social force.
DEFAULT, SOCIAL_FORCE = ("orca", False, 20, NO_SHIFT), ("social-force", False, 20, NO_SHIFT)
CONFIGURATIONS = [("mpc", "dtaci", DEFAULT), ("mpc", "none", DEFAULT),
                  ("cv-mpc", "dtaci", DEFAULT), ("cv-mpc", "none", DEFAULT),
                  ("mpc", "dtaci", SOCIAL_FORCE), ("cv-mpc", "dtaci", SOCIAL_FORCE)]
# Issue 75, in the order they run (CrowdNav++'s default first: what would the truth give
# there; then the likeliest to need a predictor): every planner, with discs and without, in
# each scenario (the default's GST and CV rows are issue 60's).
SCENARIOS = [DEFAULT, ("orca", True, 20, NO_SHIFT), ("orca", False, 20, SPEED_SHIFT),
             ("orca", False, 20, POLICY_SHIFT), ("orca", True, 35, NO_SHIFT),
             ("social-force", True, 20, NO_SHIFT), ("orca", True, 10, NO_SHIFT),
             ("social-force", True, 35, NO_SHIFT), ("social-force", True, 10, NO_SHIFT)]
# Issue 90's scenarios, by the name --scenarios takes: where a predictor could pay.
NAMED = {"default": DEFAULT, "speed": ("orca", False, 20, SPEED_SHIFT),
         "policy": ("orca", False, 20, POLICY_SHIFT)}
MATRIX = [(planner, regions, scenario) for scenario in SCENARIOS
          for planner in ("truth-mpc", "mpc", "cv-mpc", "standing-mpc")
          for regions in ("dtaci", "none")]
MODEL = "pretrained:crowdnav_sj_rand"
# Issue 90: where the crowd changes (and, to check it costs nothing there, the default task),
# the predictor trained on the task's own humans, each online correction, and the margin
# calibrated online, against CV's settings and the truth of the matrix above.
TRAINED_HERE = "pretrained:crowdnav_env"
TRAINED_PARTIAL = "pretrained:crowdnav_env_partial"
TRAINED_OBS8 = "pretrained:crowdnav_env_obs8"
ISSUE90 = [configuration for scenario in (NAMED["speed"], NAMED["policy"], DEFAULT)
           for configuration in [
               ("mpc", "none", scenario, TRAINED_HERE, "none"),
               ("mpc", "dtaci", scenario, TRAINED_HERE, "none"),
               ("mpc", "none", scenario, TRAINED_HERE, "speed-scale"),
               ("mpc", "none", scenario, TRAINED_HERE, "rls-blend"),
               ("cv-mpc", "none", scenario, MODEL, "speed-scale"),
               ("cv-mpc", "decision", scenario),
               ("mpc", "decision", scenario, TRAINED_HERE, "none")]] + [
    # The same model trained to predict people seen for part of the observation (a robot's
    # sensor range makes many; crowdnav_env predicts them 1.1-1.7 m off).
    (planner, regions, scenario, TRAINED_PARTIAL, adaptation)
    for scenario in (NAMED["speed"], NAMED["policy"], DEFAULT)
    for planner, regions, adaptation in [("mpc", "none", "none"), ("mpc", "dtaci", "none"),
                                         ("mpc", "none", "rls-blend"),
                                         ("mpc", "decision", "none"),
                                         ("mpc", "none", "speed-scale")]] + [
    # And observing 8 steps (2 s) instead of 5, so that where a person heads shows longer.
    (planner, regions, scenario, TRAINED_OBS8, "none")
    for scenario in (NAMED["speed"], NAMED["policy"], DEFAULT)
    for planner, regions in [("mpc", "none"), ("mpc", "decision")]]
# Issue 90's best configuration played again on fresh episodes (seed CONFIRM_SEED, which
# nothing was chosen on) against constant velocity's settings and the truth, in the scenario
# where it beat constant velocity on the study's episodes: it was picked as the best of many.
CONFIRM_SEED = 3000
CONFIRMED = ("mpc", "decision", NAMED["policy"], TRAINED_OBS8, "none")
CONFIRMATION = [CONFIRMED] + [(planner, regions, NAMED["policy"])
                              for planner in ("cv-mpc", "truth-mpc")
                              for regions in ("none", "dtaci", "decision")
                              if (planner, regions) != ("truth-mpc", "decision")]
# CrowdNav++'s released test logs (commit 3907731, trained_models/*/test/*.log, line 9; 500
# episodes each; path length over all episodes, navigation time over the successes).
CROWDNAV = [
    ("CrowdNav++ RL with GST (GST_predictor_rand, its log test_41665.pt.log)",
     {"success": 0.88, "collision": 0.12, "timeout": 0.00, "navigation_time_s": 14.14,
      "path_length_m": 20.08, "intrusion_ratio": 0.0835}),
    ("CrowdNav++ ORCA robot (its released log)",
     {"success": 0.69, "collision": 0.29, "timeout": 0.02, "intrusion_ratio": 0.1961}),
]


def described(configuration: tuple) -> dict:
    """A configuration's record fields (those that name its file among them): (planner,
    regions, scenario[, model, adaptation])."""
    planner, regions, (humans, reactive, num_humans, shift), *rest = configuration
    model, adaptation = rest or (MODEL, "none")
    return described_run(planner, regions, 0.1, humans, reactive, num_humans, shift, model,
                         adaptation)


def found(configuration: tuple, episodes: int, seed: int, out) -> dict | None:
    """A configuration's record, if the output folder has it (records made before issue 75
    lack its fields: they are the defaults)."""
    fields = described(configuration)
    name = record_name(fields["planner"], fields["regions"], fields["humans"], episodes, seed,
                       fields["reactive"], fields["num_humans"], fields["shift"],
                       fields["model"], fields["adaptation"])
    path = out / f"{name}.json"
    return {**fields, **json.loads(path.read_text())} if path.exists() else None


def run(configuration: tuple, episodes: int, seed: int, out) -> dict:
    record = found(configuration, episodes, seed, out)
    if record is not None:
        return record
    fields = described(configuration)
    return evaluate_described(fields, load_model(fields["model"]) if fields["model"] else None,
                              SamplingMPC.num_plans, episodes, seed, out)


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


def difference(a: dict, b: dict, episodes: int) -> tuple[float, float]:
    """a's success rate minus b's and the 95 % half-width of that difference (the two rates
    treated as independent binomials: conservative, since the episodes are the same)."""
    variance = sum(r["success"] * (1 - r["success"]) / episodes for r in (a, b))
    return a["success"] - b["success"], 1.96 * math.sqrt(variance)


def scenario_name(scenario: tuple) -> str:
    humans, reactive, num_humans, shift = scenario
    return ", ".join([f"{num_humans} {'social force' if humans == 'social-force' else 'ORCA'}",
                      "reactive" if reactive else "ignoring the robot",
                      *([{SPEED_SHIFT: "1.5x faster from 6 s",
                          POLICY_SHIFT: "ORCA to social force at 6 s"}[shift]]
                        if shift != NO_SHIFT else [])])


def matrix_table(rows: list[dict], episodes: int) -> str:
    """Issue 75's rows: scenario, predictor, discs, success with its 95 % half-width, the
    other measures."""
    lines = ["| humans | predictor | discs | success | collision | timeout | intrusion_ratio | "
             "navigation_time_s | mean_radius_m |", "|---" * 9 + "|"]
    for row in rows:
        _, half = success_half_width([row["success"]], episodes)
        lines.append(f"| {scenario_name(scenario_of(row))} | {row['predictor']} | "
                     f"{'DtACI 0.1' if row['regions'] == 'dtaci' else 'none'} | "
                     f"{row['success']:.3f} ± {half:.3f} | {row['collision']:.3f} | "
                     f"{row['timeout']:.3f} | {row['intrusion_ratio']:.3f} | "
                     f"{row['navigation_time_s']:.2f} | {row['mean_radius_m']:.3f} |")
    return "\n".join(lines)


def configuration_of(row: dict) -> tuple:
    """A record's configuration as the lists above write it: (planner, regions, scenario),
    then (model, adaptation) where they are not the matrix's."""
    model = row.get("model") or MODEL
    adaptation = row.get("adaptation", "none")
    plain = (row["planner"], row["regions"], scenario_of(row))
    return plain if (model, adaptation) == (MODEL, "none") else (*plain, model, adaptation)


def scenario_of(row: dict) -> tuple:
    return (row["humans"], row["reactive"], row["num_humans"], row["shift"])


def answers(rows: list[dict], episodes: int) -> list[str]:
    """Per scenario with all its rows: GST + discs against CV + discs, and the truth's."""
    lines = []
    for scenario in SCENARIOS:
        cell = {(r["predictor"], r["regions"]): r for r in rows if scenario_of(r) == scenario}
        if len(cell) < 8:
            continue
        gst, gst_half = difference(cell["gst", "dtaci"], cell["cv", "dtaci"], episodes)
        truth, truth_half = difference(cell["truth", "dtaci"], cell["cv", "dtaci"], episodes)
        verdict = lambda d, h: "beyond" if abs(d) > h else "within"
        lines.append(f"- {scenario_name(scenario)}: GST + discs - CV + discs {gst:+.3f} "
                     f"(half-width {gst_half:.3f}: {verdict(gst, gst_half)}); truth + discs - "
                     f"CV + discs {truth:+.3f} ({truth_half:.3f}: {verdict(truth, truth_half)}).")
    return lines


def paired_table(rows: list[dict]) -> list[str]:
    """Issue 90's answer: in each NAMED scenario, every setting against constant velocity's
    best (its setting of highest success), paired over the same episodes, and the share of the
    truth's margin over that CV each setting captures."""
    lines = ["| humans | setting | success | minus CV's best (95 % paired interval) | McNemar p "
             "| share of the truth's margin |", "|---" * 6 + "|"]
    for scenario in NAMED.values():
        # The truth's success is its margin's end (its rows, with their episodes, are
        # listed as settings: the margin itself paired).
        truths = [r for r in rows if scenario_of(r) == scenario and r["predictor"] == "truth"]
        cell = [r for r in rows if scenario_of(r) == scenario and "per_episode" in r]
        cvs = [r for r in cell if r["predictor"] == "cv"]
        if not cvs or not truths:
            continue
        best_cv = max(cvs, key=lambda r: r["success"])
        margin = max(r["success"] for r in truths) - best_cv["success"]
        for row in sorted(cell, key=lambda r: -r["success"]):
            if row is best_cv:
                lines.append(f"| {scenario_name(scenario)} | {setting(row)} (CV's best) | "
                             f"{row['success']:.3f} | | | |")
                continue
            success = compare(row, best_cv)["success"]
            share = success["difference"] / margin if margin > 0 else math.nan
            lines.append(f"| {scenario_name(scenario)} | {setting(row)} | {row['success']:.3f} "
                         f"| {success['difference']:+.3f} ({success['low']:+.3f} to "
                         f"{success['high']:+.3f}) | {success['p']:.2g} | {share:+.2f} |")
    return lines if len(lines) > 2 else []


def confirmation_lines(runs, episodes: int) -> list[str]:
    """CONFIRMED against constant velocity's best and the truth's best on the CONFIRMATION
    episodes, paired, where all of them are made."""
    records = [found(c, episodes, CONFIRM_SEED, runs) for c in CONFIRMATION]
    if any(r is None for r in records):
        return []
    confirmed, others = records[0], records[1:]
    best_cv = max((r for r in others if r["predictor"] == "cv"), key=lambda r: r["success"])
    best_truth = max((r for r in others if r["predictor"] == "truth"),
                     key=lambda r: r["success"])
    success = compare(confirmed, best_cv)["success"]
    margin = best_truth["success"] - best_cv["success"]
    return [f"Played again on {episodes} fresh episodes (seed {CONFIRM_SEED} on, on which "
            f"nothing was chosen), {setting(confirmed)} succeeds {confirmed['success']:.3f} "
            f"against constant velocity's best there, {setting(best_cv)} "
            f"{best_cv['success']:.3f}: {success['difference']:+.3f} ({success['low']:+.3f} to "
            f"{success['high']:+.3f}, McNemar p {success['p']:.2g}), "
            f"{success['difference'] / margin:.2f} of the truth's margin ({setting(best_truth)} "
            f"{best_truth['success']:.3f}). Constant velocity's settings there: "
            + ", ".join(f"{setting(r)} {r['success']:.3f}" for r in others
                        if r["predictor"] == "cv") + ".", ""]


def readings(default: list[dict], episodes: int) -> list[str]:
    """`reading` and `among_social_force` of issue 60's rows, where all of them are made."""
    orca = [r for r in default if r["humans"] == "orca"]
    social_force = [r for r in default if r["humans"] != "orca"]
    if (len(orca), len(social_force)) != (4, 2):
        return []
    return [reading(orca, episodes) + " " + among_social_force(social_force, episodes), ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--tabulate", action="store_true", help="run nothing: tabulate the "
                        "records the output folder holds and name the configurations missing")
    parser.add_argument("--scenarios", nargs="+", choices=tuple(NAMED), help="run only the "
                        "configurations of these scenarios (default: all)")
    parser.add_argument("--issue90", action="store_true", help="run only issue 90's "
                        "configurations")
    parser.add_argument("--reverse", action="store_true", help="run them last first (a second "
                        "process beside one running them in order)")
    parser.add_argument("--confirm", action="store_true", help="run only issue 90's best "
                        f"configuration and its comparisons on fresh episodes (seed "
                        f"{CONFIRM_SEED})")
    add_results_flags(parser, "navigation", "the records and navigation.md", runs=False)
    args = parser.parse_args()
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    runs = out / "runs" / "navigation" if args.publish else out
    runs.mkdir(parents=True, exist_ok=True)
    rows, missing, seconds = [], [], []
    everything = CONFIGURATIONS + [c for c in MATRIX + ISSUE90 if c not in CONFIGURATIONS]
    # The truth's rows run last, smallest crowds first: they simulate the crowd once more for
    # every prediction (70 min for 500 episodes among 35 reactive humans, against about 2 for
    # the others), so a study stopped early keeps the most of them.
    in_order = sorted(everything, key=lambda c: (c[0] == "truth-mpc") * (1 + c[2][2]))
    if args.issue90:
        in_order = [c for c in in_order if c in ISSUE90]
    if args.scenarios:
        in_order = [c for c in in_order if c[2] in [NAMED[name] for name in args.scenarios]]
    if args.reverse:
        in_order = in_order[::-1]
    seed = CONFIRM_SEED if args.confirm else args.seed
    if args.confirm:
        in_order = CONFIRMATION
    for done, configuration in enumerate([] if args.tabulate else in_order):
        if found(configuration, args.episodes, seed, runs) is None:
            started = time.perf_counter()
            record = run(configuration, args.episodes, seed, runs)
            seconds.append(time.perf_counter() - started)
            left = sum(found(c, args.episodes, seed, runs) is None for c in in_order)
            print(f"[{done + 1}/{len(in_order)}] {row_label(record)}: success "
                  f"{record['success']:.3f}, {seconds[-1]:.0f} s; {left} left, about "
                  f"{left * sum(seconds) / len(seconds) / 3600:.1f} h at this pace", flush=True)
    for configuration in everything:
        record = found(configuration, args.episodes, args.seed, runs)
        if record is None:
            fields = described(configuration)
            missing.append(f"{configuration[0]} {configuration[1]} "
                           f"({scenario_name(configuration[2])}"
                           + (f"; {setting(fields)}" if len(configuration) > 3 else "") + ")")
            continue
        rows.append({**record, "label": row_label(record)})
    default = [r for r in rows if configuration_of(r) in CONFIGURATIONS]
    matrix = [r for r in rows if configuration_of(r) in MATRIX]
    published = rows + [{"label": f"{name} | | | ORCA", **figures}
                        for name, figures in CROWDNAV]
    text = "\n".join([
        "# Planning against GST's calibrated predictions in CrowdNav++'s task", "",
        f"Made by `python experiments/navigation.py --publish`: {args.episodes} test episodes "
        f"(seed {args.seed} on, the same for every row) of `gst_jax.simulate.crowdnav.environment."
        "CrowdNav` (CrowdNav++'s default task: 20 ORCA humans who ignore the robot, 0.25 s "
        "steps, 50 s; in the rows marked so, its social-force humans instead), "
        "docs/navigation.md. Navigation time over the successful episodes, path "
        "length over all, intrusion ratio: the share of an episode's steps in which a human's "
        "next 5 positions come within 0.6 m of the robot; mean radius: of the discs the "
        "planner was given.", "",
        format_table(default + published[len(rows):]), "",
        *readings(default, args.episodes),
        "CrowdNav++'s rows are its released test logs (its RL policy with GST, trained over "
        "20 M steps; 500 episodes of its own simulator, whose rules this environment follows "
        "but for the four differences of docs/navigation.md), not runs here: other episodes. "
        "ICP (tedhuang96/icp, WAFR 2024) publishes no results in its repository and its "
        "paper's table could not be read here; its simulator differs (5-10 humans who react "
        "to the robot, radius 0.4 m).", "",
        "## When would a predictor help? Humans who react, crowds, shifts (issue 75)", "",
        "The same planner against four predictors: none (people standing where they are), "
        "constant velocity (cv), GST (crowdnav_sj_rand) and the simulator's own next positions "
        "(truth: every human moved on by the environment's rules with its goal kept and the "
        "robot at its velocity; exact but for goal changes and replaced humans, so no "
        "predictor can do better), each with DtACI discs (alpha 0.1) and without. Reactive "
        "humans see the robot as one more agent (CrowdNav++'s `robot.visible`); a shift begins "
        "6 s into every episode. ± is the binomial 95 % half-width of the success rate.", "",
        matrix_table(matrix, args.episodes), "",
        "Success differences (half-width of the difference, the rates taken as independent):",
        "", *answers(matrix, args.episodes), "",
        *(["## Paired over the same episodes (issue 90)", "",
           "Each setting against constant velocity's best in the same scenario, episode by "
           "episode: the difference in success with its 95 % paired-bootstrap interval and "
           "McNemar's exact p, and the share of the truth's margin over that CV (the best "
           "truth setting's success minus CV's best) it captures.", "",
           *paired_table(rows), "", *confirmation_lines(runs, args.episodes)]
          if paired_table(rows) else []),
        *([f"Not yet run ({len(missing)}): " + "; ".join(missing) + ".", ""] if missing
          else [])])
    (out / "navigation.md").write_text(text)
    (out / "navigation.json").write_text(json.dumps(published, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
