"""Does sparsity keep the robot from freezing? The study's models against random encounters
(issue 59, step 4; the paper's Fig. 5(d) claim):

    python experiments/encounters.py --study runs/study/eth             # runs/encounters/
    python experiments/encounters.py --study runs/study/eth --publish   # results/encounters.*

Every finished member of the study (work directories named n{N}-{partial|full}-seed{S}
under --study, N = 0 for full connection), the shipped `crowd_d` and the robot driven by
constant velocity meet the same `--episodes` random encounters
(`gst_jax.simulate.encounters`, seed 0), each model in one jitted program over all of them;
a member's episodes are kept in its work directory (encounters/), so a rerun simulates only the
members that finished since.
Per model: the rates of freezing or turning back, of collisions and of arrival with Wilson
95 % intervals, time to goal and path length ratio. The claim is judged on paired
differences: per seed and detection mode, member n minus member F on the same episodes, with
its 95 % interval (a paired difference of proportions); the table says for how many of the
pairs sparsity froze less, and for how many the interval excludes 0.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path

import numpy as np
from _common import add_results_flags, results_folder

from gst_jax.runs import load_model
from gst_jax.simulate.encounters import format_encounters
from gst_jax.simulate.loop import constant_velocity_model
from gst_jax.simulate.study import run_encounter_study, step_models, time_grid

MEMBER = re.compile(r"n(\d+)-(partial|full)-seed(\d+)$")


def members(study: Path) -> dict[str, Path]:
    """The study's finished members (an evaluation written), by label 'n=1 partial 1000', in
    the order of n, detection mode and seed."""
    found = {}
    for workdir in study.iterdir():
        match = MEMBER.match(workdir.name)
        if match and workdir.is_dir() and any((workdir / "eval").glob("*.json")):
            n, mode, seed = match.groups()
            found[(int(n), mode, int(seed))] = (f"n={n if n != '0' else 'F'} {mode} {seed}",
                                                workdir)
    return dict(found[key] for key in sorted(found))


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """mean(a) - mean(b) of paired 0/1 outcomes and its 95 % interval (Wald, paired)."""
    count = len(a)
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(~a & b))
    difference = (only_a - only_b) / count
    half = 1.96 * math.sqrt(max(only_a + only_b - (only_a - only_b) ** 2 / count, 0)) / count
    return difference, difference - half, difference + half


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--study", type=Path, required=True,
                        help="folder of the study's member work directories")
    parser.add_argument("--episodes", type=int, default=1000,
                        help="random encounters per model (default: 1000)")
    add_results_flags(parser, "encounters", "encounters.json/.md/.png", runs=False)
    args = parser.parse_args(argv)
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    found = members(args.study)
    runs = {label: load_model(str(workdir)) for label, workdir in found.items()}
    runs["crowd_d"] = load_model("pretrained:crowd_d")
    labels = ["constant velocity", *runs]
    models = [constant_velocity_model] + [step_models([run])[-1][1] for run in runs.values()]
    # A member's episodes are kept in its work directory: a rerun simulates only new members.
    stored = {label: workdir / "encounters" / f"{args.episodes}-seed0.json"
              for label, workdir in found.items()}
    summaries, rows = run_encounter_study(list(zip(labels, models)), args.episodes, out,
                                          grid=time_grid(list(runs.values())), stored=stored)
    froze = {label: np.array([r["freezing_or_u_turn"] for r in rows[label]])
             for label in labels}
    pairs = []
    for label in found:
        n, mode, seed = label.split()
        full = f"n=F {mode} {seed}"
        if n != "n=F" and full in froze:
            pairs.append({"sparse": label, "full": full,
                          "freezing_difference": paired_difference(froze[label], froze[full])})
    record = {"episodes": args.episodes, "seed": 0, "scene": args.study.name,
              "members": list(found),
              "models": summaries, "pairs": pairs}
    (out / "encounters.json").write_text(json.dumps(record, indent=1) + "\n")
    (out / "encounters.md").write_text(markdown(record))
    print(json.dumps(record, indent=1) if args.json else markdown(record))


def markdown(record: dict) -> str:
    """The record as results/encounters.md."""
    lines = [f"# {record['episodes']} random encounters per model", "",
             f"Made by `python experiments/encounters.py --study runs/study/{record['scene']} "
             f"--publish`: the study's finished {record['scene']} members "
             f"({', '.join(record['members'])}; 200 epochs), "
             "`crowd_d` and constant velocity on the same episodes (seed 0). Rates with Wilson "
             "95 % intervals; time to goal over the episodes that arrived; episodes/s after "
             "compiling, on the 2-core VM beside the study's two trainings.", "",
             format_encounters(record["models"]), "",
             "| sparse member | full connection | freezing: sparse - full [95 %] |",
             "|---|---|---|"]
    pairs = record["pairs"]
    for pair in pairs:
        value, low, high = pair["freezing_difference"]
        lines.append(f"| {pair['sparse']} | {pair['full']} | {value:+.3f} "
                     f"[{low:+.3f}, {high:+.3f}] |")
    fewer = sum(p["freezing_difference"][0] < 0 for p in pairs)
    clearly_fewer = sum(p["freezing_difference"][2] < 0 for p in pairs)
    clearly_more = sum(p["freezing_difference"][1] > 0 for p in pairs)
    lines += ["", f"Sparsity froze less in {fewer} of {len(pairs)} pairs; the interval lies "
              f"below 0 in {clearly_fewer} and above 0 in {clearly_more}."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
