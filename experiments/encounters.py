"""Does sparsity keep the robot from freezing? The study's models against random encounters
(issue 59, step 4; the paper's Fig. 5(d) claim):

    python experiments/encounters.py --study runs/study/eth             # runs/encounters/
    python experiments/encounters.py --study runs/study/eth --publish   # results/encounters.*

Every finished member of the study (work directories named n{N}-{partial|full}-seed{S}
under --study, N = 0 for full connection), the shipped `crowd_d` and the robot driven by
constant velocity meet the same `--episodes` random encounters
(`gst_jax.simulate.paper.encounters`, seed 0), each model in one jitted program over all of them;
a member's episodes are kept in its work directory (encounters/), so a rerun simulates only the
members that finished since. The members of the record already written (results/ with
--publish) whose work directories are gone, another sitting's or a fresh clone's, keep their
rates and, recorded per episode, whether they froze.
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
from _study import encounter_label
from gst_jax.config import Member
from gst_jax.runs import load_model
from gst_jax.simulate.agents.predicted import constant_velocity_model
from gst_jax.simulate.paper.encounters import format_encounters
from gst_jax.simulate.paper.study import (
    draw_encounter_rates,
    run_encounter_study,
    step_models,
    time_grid,
)

MEMBER = re.compile(r"n(\d+)-(partial|full)-seed(\d+)$")


def members(study: Path) -> dict[str, Path]:
    """The study's finished members (an evaluation written), by label 'n=1 partial 1000', in
    the order of n, detection mode and seed."""
    found = {}
    for workdir in study.iterdir():
        match = MEMBER.match(workdir.name)
        if match and workdir.is_dir() and any((workdir / "eval").glob("*.json")):
            n, mode, seed = match.groups()
            member = Member(int(n), mode == "full", int(seed))
            found[(member.edge_heads, mode, member.seed)] = (encounter_label(member), workdir)
    return dict(found[key] for key in sorted(found))


def member_order(label: str) -> tuple[int, str, int]:
    """Sort key of a member's label 'n=F partial 1000': n (F first), detection mode, seed."""
    n, mode, seed = label.split()
    return (0 if n == "n=F" else int(n[2:]), mode, int(seed))


def _difference(only_a: int, only_b: int, count: int) -> tuple[float, float, float]:
    """Paired difference of proportions from its discordant counts, with its 95 % interval
    (Wald, paired)."""
    difference = (only_a - only_b) / count
    half = 1.96 * math.sqrt(max(only_a + only_b - (only_a - only_b) ** 2 / count, 0)) / count
    return difference, difference - half, difference + half


def paired_difference(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float]:
    """mean(a) - mean(b) of paired 0/1 outcomes and its 95 % interval (Wald, paired)."""
    return _difference(int(np.sum(a & ~b)), int(np.sum(~a & b)), len(a))


def widest_paired_difference(rate_a: float, rate_b: float, count: int
                             ) -> tuple[float, float, float]:
    """The paired difference of two rates over the same `count` episodes when the episodes
    of one are lost: exact, with the widest interval the rates allow (the fewest episodes
    where both happened)."""
    a, b = round(rate_a * count), round(rate_b * count)
    both = max(0, a + b - count)
    return _difference(a - both, b - both, count)


def earlier_record(path: Path, episodes: int, scene: str) -> dict:
    """The record at `path` if it met the same encounters in the same scene, else {}."""
    record = json.loads(path.read_text()) if path.is_file() else {}
    same = record.get("episodes") == episodes and record.get("scene") == scene
    return record if same else {}


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
    earlier = earlier_record(out / "encounters.json", args.episodes, args.study.name)
    runs = {label: load_model(str(workdir)) for label, workdir in found.items()}
    runs["crowd_d"] = load_model("pretrained:crowd_d")
    labels = ["constant velocity", *runs]
    models = [constant_velocity_model] + [step_models([run])[-1][1] for run in runs.values()]
    # A member's episodes are kept in its work directory: a rerun simulates only new members.
    stored = {label: workdir / "encounters" / f"{args.episodes}-seed0.json"
              for label, workdir in found.items()}
    simulated, rows = run_encounter_study(list(zip(labels, models)), args.episodes, out,
                                          grid=time_grid(list(runs.values())), stored=stored)
    froze = {label: "".join("01"[bool(r["freezing_or_u_turn"])] for r in rows[label])
             for label in found}
    gone = [label for label in earlier.get("members", []) if label not in found]
    froze |= {label: earlier["froze"][label] for label in gone
              if label in earlier.get("froze", {})}
    study = sorted([*found, *gone], key=member_order)
    summaries = {"constant velocity": simulated["constant velocity"],
                 **{label: simulated.get(label) or earlier["models"][label] for label in study},
                 "crowd_d": simulated["crowd_d"]}
    published = {(p["sparse"], p["full"]): p for p in earlier.get("pairs", [])}
    pairs = []
    for label in study:
        n, mode, seed = label.split()
        full = f"n=F {mode} {seed}"
        if n == "n=F" or full not in summaries:
            continue
        if label in froze and full in froze:
            as_flags = [np.array([c == "1" for c in froze[m]]) for m in (label, full)]
            pairs.append({"sparse": label, "full": full,
                          "freezing_difference": paired_difference(*as_flags)})
        elif (label, full) in published:
            pairs.append(published[(label, full)])
        else:     # episodes lost with a work directory before they were recorded per episode
            rates = [summaries[m]["freezing_or_u_turn"][0] for m in (label, full)]
            pairs.append({"sparse": label, "full": full, "paired": False,
                          "freezing_difference": widest_paired_difference(*rates,
                                                                          args.episodes)})
    record = {"episodes": args.episodes, "seed": 0, "scene": args.study.name,
              "members": study, "models": summaries, "pairs": pairs, "froze": froze}
    (out / "encounters.json").write_text(json.dumps(record, indent=1) + "\n")
    (out / "encounters.md").write_text(markdown(record))
    if gone:      # drawn again with the members simulated before
        draw_encounter_rates(summaries, args.episodes, 0, out)
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
                     f"[{low:+.3f}, {high:+.3f}]{'' if pair.get('paired', True) else ' *'} |")
    fewer = sum(p["freezing_difference"][0] < 0 for p in pairs)
    clearly_fewer = sum(p["freezing_difference"][2] < 0 for p in pairs)
    clearly_more = sum(p["freezing_difference"][1] > 0 for p in pairs)
    lines += ["", f"Sparsity froze less in {fewer} of {len(pairs)} pairs; the interval lies "
              f"below 0 in {clearly_fewer} and above 0 in {clearly_more}."]
    if not all(p.get("paired", True) for p in pairs):
        lines += ["", "\\* The full-connection member's episodes were lost with its work "
                  "directory before they were recorded one by one: the difference of the two "
                  "rates is exact, the interval the widest they allow."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
