"""The general model: GST trained on every bundled scene at once, scored on each scene's test split.

    python experiments/crowd.py --train                      # GST (D): train or resume, evaluate
    python experiments/crowd.py --train --output gaussian    # GST (P)
    python experiments/crowd.py --park                       # keep the newest checkpoint
    python experiments/crowd.py --publish                    # the published results/crowd.md
    python -m gst_jax.pretrained export runs/crowd-paper-d-n1-e200-seed1000 --name crowd_d

The run is `python -m gst_jax.train --scene crowd --protocol paper --output O --epochs E
--seed s` (n = 1, ghost): its train split is the union of the paper train splits of the five
ETH/UCY scenes, LCAS and WILDTRACK. `--train` runs or resumes it as `experiments/table1.py`
does (same parking in parked/), then evaluates it on every scene's test split, as
`python -m gst_jax.evaluate RUN --scene S` does. Writes <out>/crowd[_p].md and .json: per
scene, the general model beside that scene's own Table I model (its record in <out>/runs/, or
the shipped model; seed 1000) and constant velocity; the run's record
<out>/runs/<run name>.json keeps the per-scene metrics. <out> is runs/crowd/ (or --workdir);
`--publish` makes it the checkout's results/, whose committed records then count as finished
runs (experiments/table1.py).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from _common import PARKED, add_results_flags, evaluate, park, results_folder
from gst_jax import pretrained
from gst_jax.config import CROWD, CROWD_SCENES, ETH_UCY_SCENES, DataConfig
from gst_jax.io.workdir import WorkDir
from table1 import run_scene_seed, train_flags, workdir_of

SCENES = CROWD_SCENES
OWN_MODEL_SEED = 1000


def per_scene_metrics(workdir: Path, epochs: int, evaluate_missing: bool) -> dict[str, dict]:
    """The run's test metrics on each scene it was evaluated on (evaluating the missing ones
    first if `evaluate_missing`)."""
    found = {}
    for scene in SCENES:
        config = DataConfig(scene=scene)
        if evaluate_missing and WorkDir(workdir).read_evaluation(config, "test", epochs) is None:
            evaluate(workdir, config)
        if (result := WorkDir(workdir).read_evaluation(config, "test", epochs)) is not None:
            found[scene] = result
    return found


def crowd_record(runs: Path, records: Path, output: str, epochs: int, seed: int, train: bool,
                 checkpoint_every: int, parked_runs: Path,
                 drop_parked: bool = False) -> dict | None:
    """The general run's record (its union test metrics, see table1.run_scene_seed) with
    "per_scene": its test metrics on every scene evaluated so far."""
    record = run_scene_seed(runs, records, CROWD, "paper", output, epochs, seed, train,
                            checkpoint_every, parked_runs, drop_parked=drop_parked)
    if record is None:
        return None
    workdir = workdir_of(runs, CROWD, "paper", output, epochs, seed)
    record_path = records / f"{workdir.name}.json"
    if workdir.is_dir():
        record["per_scene"] = per_scene_metrics(workdir, epochs, evaluate_missing=train)
        record_path.write_text(json.dumps(record, indent=2) + "\n")
    elif record["workdir"].startswith("gst_jax/pretrained/"):      # the shipped model's
        name = Path(record["workdir"]).name
        record["per_scene"] = pretrained.load_meta(name).get("test_metrics_per_scene", {})
    return record


def rows(record: dict | None, runs: Path, records: Path, output: str, epochs: int) -> list[dict]:
    """One row per scene: the general model, the scene's own model, constant velocity."""
    per_scene = (record or {}).get("per_scene", {})
    table = []
    for scene in SCENES:
        row = {"scene": scene}
        if (general := per_scene.get(scene)) is not None:
            row.update(aoe=general["aoe"], foe=general["foe"], pedestrians=general["pedestrians"],
                       cv_aoe=general["cv_aoe"], cv_foe=general["cv_foe"])
        if scene in ETH_UCY_SCENES and (own := run_scene_seed(
                runs, records, scene, "paper", output, epochs, OWN_MODEL_SEED,
                train_missing=False)):
            row.update(own_aoe=own["aoe"], own_foe=own["foe"])
        table.append(row)
    if record is not None:
        table.append({"scene": "all seven", "aoe": record["aoe"], "foe": record["foe"],
                      "pedestrians": record["pedestrians"], "cv_aoe": record["cv_aoe"],
                      "cv_foe": record["cv_foe"]})
    return table


def markdown(table: list[dict], record: dict | None, output: str, epochs: int,
             command: str) -> str:
    name = "GST (P)" if output == "gaussian" else "GST (D)"
    pair = lambda row, a, f: f"{row[a]:.3f} / {row[f]:.3f}" if a in row else "-"
    lines = [f"# The general model, {name}: trained on all seven scenes", "",
             f"`{command}`: n = 1, ghost, {epochs} epochs, trained on the union of the paper "
             "train splits of ETH, HOTEL, UNIV, ZARA1, ZARA2, LCAS and WILDTRACK. AOE / FOE "
             "in metres on the fully detected pedestrians of each scene's paper test split, "
             "mean over 20 evaluation runs. Own model: the scene's Table I run (trained on "
             f"that scene alone, seed {OWN_MODEL_SEED}; none is trained for LCAS and "
             "WILDTRACK). CV: constant velocity on the same pedestrians.", ""]
    if record is None:
        lines += ["Not trained yet: `python experiments/crowd.py --train"
                  + (" --output gaussian" if output == "gaussian" else "") + "`.", ""]
    elif record.get("train_time_s"):
        lines += [f"Train time {record['train_time_s'] / 60:.0f} min (summed epoch times), "
                  f"code {', '.join(record.get('code') or ['?'])}.", ""]
    if record is not None and record.get("note"):        # what the record's history adds
        lines += [record["note"], ""]
    lines += ["| test split | pedestrians | general model AOE / FOE | own model AOE / FOE | "
              "CV AOE / FOE |", "|---|---|---|---|---|"]
    for row in table:
        lines.append(f"| {row['scene']} | {row.get('pedestrians', '-')} | "
                     f"{pair(row, 'aoe', 'foe')} | {pair(row, 'own_aoe', 'own_foe')} | "
                     f"{pair(row, 'cv_aoe', 'cv_foe')} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", default="deterministic", choices=("deterministic", "gaussian"),
                        help="GST (D) or GST (P) (default: deterministic)")
    parser.add_argument("--epochs", type=int, default=200, help="epochs (default: 200)")
    parser.add_argument("--seed", type=int, default=1000, help="training seed (default: 1000)")
    parser.add_argument("--train", action="store_true",
                        help="train (or resume) and evaluate the run on every scene")
    parser.add_argument("--checkpoint-every", type=int, default=5,
                        help="epochs between checkpoints when training (default: 5)")
    parser.add_argument("--park", action="store_true",
                        help="copy the unfinished run's newest checkpoint into "
                             "--parked (commit it to continue in another sitting)")
    parser.add_argument("--parked", type=Path, default=PARKED,
                        help=f"folder of parked runs (default: {PARKED})")
    add_results_flags(parser, "crowd", "crowd[_p].md/.json and the run's record runs/*.json")
    args = parser.parse_args(argv)
    runs, out = Path(args.runs), results_folder(args)
    records = out / "runs"
    workdir = workdir_of(runs, CROWD, "paper", args.output, args.epochs, args.seed)
    if args.park:
        if epoch := park(workdir, args.parked / workdir.name):
            print(f"parked {workdir.name} after epoch {epoch}", file=sys.stderr)
        return

    record = crowd_record(runs, records, args.output, args.epochs, args.seed, args.train,
                          args.checkpoint_every, args.parked, drop_parked=args.publish)
    table = rows(record, runs, records, args.output, args.epochs)
    command = " ".join(["python -m gst_jax.train",
                        *train_flags(CROWD, "paper", args.output, args.epochs, args.seed)])
    stem = "crowd" + ("_p" if args.output == "gaussian" else "")
    out.mkdir(parents=True, exist_ok=True)
    text = markdown(table, record, args.output, args.epochs, command)
    (out / f"{stem}.md").write_text(text)
    (out / f"{stem}.json").write_text(json.dumps(table, indent=2) + "\n")
    print(json.dumps(table, indent=2) if args.json else text)
    print(f"written: {out / stem}.md, .json", file=sys.stderr)


if __name__ == "__main__":
    main()
