"""Table I of the paper: train (or reuse), evaluate and tabulate GST on the five ETH/UCY scenes.

    python experiments/table1.py                       # tabulate what runs/ holds
    python experiments/table1.py --train --seeds 1000,1001,1002 --scenes eth
    python experiments/table1.py --protocol loo --train
    python experiments/table1.py --publish --seeds 1000,1001,1002   # the published table

Each (scene, seed) is the work directory of `python -m gst_jax.train --scene S --protocol P
--output O --epochs E --seed s` under --runs (n = 1, ghost: the paper's configuration).
`--train` trains or resumes that run where it is incomplete, then evaluates it with the
paper protocol (20 runs), as `python -m gst_jax.evaluate` does. Every finished evaluation is
also kept as a small record in <out>/runs/<run name>.json, so the table survives the loss of
the work directories. Scenes without a finished evaluation are listed as missing (with the
epoch an unfinished run has reached), never filled in; without --train a scene's seed-1000
row falls back to the test metrics of the shipped model trained by the same command. Writes
<out>/table1[_loo][_p].md, .json and a .png of the bars per scene.

<out> is runs/table1/ (or --workdir). `--publish` makes it the checkout's results/: it
rewrites the published tables, and the records committed in results/runs/ count as
finished runs (without it they do not, so `--train` trains what --runs lacks).

A run longer than one sitting (univ on two CPU cores) continues in the next one: `--park`
copies the newest checkpoint of every unfinished run into <parked>/<run name>/, to be
committed; `--train` on a machine without the work directory starts from that copy, and with
--publish the copy is deleted once the run's evaluation is recorded in results/runs/.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from _common import (
    PARKED,
    add_results_flags,
    evaluate,
    latest_checkpoint,
    park,
    results_folder,
    train,
)
from _figures import table1_against_paper
from gst_jax import data, pretrained
from gst_jax.config import ETH_UCY_SCENES, DataConfig, ModelConfig, TrainConfig
from gst_jax.evaluation import constant_velocity_baseline
from gst_jax.io.workdir import WorkDir, run_name
from gst_jax.model.heads import head

# docs/MODEL.md 4: the paper's Table I (AOE / FOE in metres, fully detected pedestrians).
PAPER = {
    "deterministic": {"eth": (0.96, 2.09), "hotel": (0.21, 0.38), "univ": (0.50, 1.08),
                      "zara1": (0.40, 0.86), "zara2": (0.32, 0.70)},
    "gaussian": {"eth": (1.10, 2.22), "hotel": (0.22, 0.37), "univ": (0.64, 1.32),
                 "zara1": (0.59, 1.15), "zara2": (0.46, 0.95)},
}


def workdir_of(runs: Path, scene: str, protocol: str, output: str, epochs: int,
               seed: int, schedule: str = TrainConfig.schedule) -> Path:
    """The work directory `python -m gst_jax.train` picks for this run by default."""
    return runs / run_name(DataConfig(scene=scene, protocol=protocol), ModelConfig(output=output),
                           TrainConfig(epochs=epochs, seed=seed, schedule=schedule))


def train_flags(scene: str, protocol: str, output: str, epochs: int,
                seed: int | str, schedule: str = TrainConfig.schedule) -> list[str]:
    """The flags of `python -m gst_jax.train` for one run of the table."""
    flags = ["--scene", scene, "--protocol", protocol, "--output", output,
             "--epochs", str(epochs), "--seed", str(seed)]
    return flags if schedule == TrainConfig.schedule else [*flags, "--schedule", schedule]


def shipped_record(scene: str, protocol: str, output: str, epochs: int,
                   seed: int, schedule: str = TrainConfig.schedule) -> dict | None:
    """The test metrics recorded with a shipped pretrained model of exactly this run."""
    name = f"{scene}_{head(output).letter}"                          # e.g. eth_d, eth_p
    if name not in pretrained.available():
        return None
    meta = pretrained.load_meta(name)
    trained = (meta["data"]["protocol"], meta["train"]["epochs"], meta["train"]["seed"],
               meta["train"].get("schedule", TrainConfig.schedule))
    if trained != (protocol, epochs, seed, schedule) or meta["model"]["num_edge_heads"] != 1:
        return None
    return {**meta["test_metrics"], "workdir": f"gst_jax/pretrained/{name}",
            "train_time_s": meta.get("train_time_s"), "code": meta.get("code")}


def run_scene_seed(runs: Path, records: Path, scene: str, protocol: str, output: str,
                   epochs: int, seed: int, train_missing: bool,
                   checkpoint_every: int = TrainConfig.checkpoint_every,
                   parked_runs: Path = PARKED,
                   schedule: str = TrainConfig.schedule,
                   drop_parked: bool = False) -> dict | None:
    """Evaluation and training time of one run: its work directory's final evaluation (kept as
    a record in `records`), else that record, else if `train_missing` a new run (trained and
    evaluated in its work directory under `runs`), else the record of the shipped model
    trained by the same command. `drop_parked`: delete the run's parked copy once it is
    recorded (when `records` are the published ones, committed in its place)."""
    workdir = workdir_of(runs, scene, protocol, output, epochs, seed, schedule)
    record_path = records / f"{workdir.name}.json"
    parked = parked_runs / workdir.name
    data_config = DataConfig(scene=scene, protocol=protocol)
    if (result := WorkDir(workdir).read_evaluation(data_config, "test", epochs)) is not None:
        record = {**result, "seed": seed, "workdir": str(workdir),
                  "train_time_s": WorkDir(workdir).training_time_s(),
                  "code": WorkDir(workdir).code_versions()}
        records.mkdir(parents=True, exist_ok=True)
        record_path.write_text(json.dumps(record, indent=2) + "\n")
        if drop_parked:
            shutil.rmtree(parked, ignore_errors=True)
        return record
    if record_path.exists():
        return json.loads(record_path.read_text())
    if not train_missing:
        record = shipped_record(scene, protocol, output, epochs, seed, schedule)
        return None if record is None else {**record, "seed": seed}
    if parked.is_dir() and not (workdir / "checkpoints").is_dir():
        shutil.copytree(parked, workdir)                # continue another sitting's run
    train(ModelConfig(output=output), data_config, TrainConfig(
        epochs=epochs, seed=seed, checkpoint_every=checkpoint_every, schedule=schedule), workdir)
    evaluate(workdir)
    return run_scene_seed(runs, records, scene, protocol, output, epochs, seed,
                          train_missing=False, parked_runs=parked_runs, schedule=schedule,
                          drop_parked=drop_parked)


def trained_epochs(runs: Path, parked_runs: Path, scene: str, protocol: str, output: str,
                   epochs: int, seed: int) -> int | None:
    """How far an unfinished run has got: the newest checkpoint of its work directory or of
    its parked copy (None: not started)."""
    workdir = workdir_of(runs, scene, protocol, output, epochs, seed)
    found = [latest_checkpoint(path) for path in (workdir, parked_runs / workdir.name)]
    return max((epoch for epoch in found if epoch is not None), default=None)


def summarize(scene: str, output: str, per_seed: list[dict], command: str,
              baseline: dict, in_progress: dict[int, int] | None = None) -> dict:
    """One table row: mean over seeds; spread = std over seeds (one seed: over its 20 runs).
    baseline: `constant_velocity_baseline` on the scene's test split, shown for every
    scene, finished or not; in_progress: seed -> epochs trained, of a scene without a
    finished run."""
    paper_aoe, paper_foe = PAPER[output][scene]
    row = {"scene": scene, "paper_aoe": paper_aoe, "paper_foe": paper_foe, "command": command,
           **baseline}
    if not per_seed:
        if in_progress:
            row["in_progress"] = {str(seed): epoch for seed, epoch in in_progress.items()}
        return row
    for name in ("aoe", "foe"):
        values = np.array([r[name] for r in per_seed])
        row[name] = float(values.mean())
        row[f"{name}_spread"] = (float(values.std()) if len(values) > 1
                                 else float(per_seed[0][f"{name}_std"]))
    release = [(r.get("release_aoe_std"), r.get("release_foe_std")) for r in per_seed]
    row["release_spread"] = (None if any(None in pair for pair in release)
                             else [float(np.mean(values)) for values in zip(*release)])
    kde = [r.get("kde_nll") for r in per_seed]
    row.update(kde_nll=None if None in kde else float(np.mean(kde)),
               seeds=[r["seed"] for r in per_seed], spread_over="seeds" if len(per_seed) > 1
               else "20 runs", epoch=per_seed[0]["epoch"], protocol=per_seed[0]["protocol"],
               train_time_s=[r["train_time_s"] for r in per_seed],
               per_seed={str(r["seed"]): {"aoe": r["aoe"], "foe": r["foe"],
                                          "workdir": r["workdir"], "code": r.get("code"),
                                          **({"note": r["note"]} if "note" in r else {})}
                         for r in per_seed})
    return row


def markdown(rows: list[dict], output: str, protocol: str, epochs: int) -> str:
    gaussian = output == "gaussian"
    kde_head, kde_rule = (" KDE-NLL |", "---|") if gaussian else ("", "")
    lines = [f"# Table I, {'GST (P)' if gaussian else 'GST (D)'}, {protocol} protocol", "",
             f"n = 1, ghost, {epochs} epochs; AOE / FOE in metres on fully detected pedestrians "
             "of the test split. Ours: each run's value is the mean over 20 evaluation runs (hard "
             "samples, tau 0.03" + ("; each run samples the Gaussians too" if gaussian else "")
             + "); ± is the std over seeds, or over the 20 runs for one seed. "
             + ("KDE-NLL of the 20 samples (Trajectron++ rule; the paper gives only its "
                "average, -1.98). " if gaussian else "")
             + "Release ±: the release's own spread statistic (its eval.py: per-window std "
             "over the 20 runs, summed, per pedestrian; mean over seeds; '-' for records made "
             "before it was computed), comparable with the paper's ± columns. "
             "CV: constant velocity on the same pedestrians. Train time: summed epoch times "
             "(metrics.jsonl) on the machine that trained the run, per seed."
             + (" The paper did not report this protocol: its columns are its Table I (paper "
                "split), for orientation only, not a like-for-like comparison."
                if protocol != "paper" else ""), "",
             f"| scene | ours AOE | ours FOE | release ± | paper AOE | paper FOE |{kde_head} "
             "CV AOE / FOE | seeds | train time | command |",
             f"|---|---|---|---|---|---|{kde_rule}---|---|---|---|"]
    for r in rows:
        paper = f"{r['paper_aoe']:.2f} | {r['paper_foe']:.2f} |"
        cv = f"{r['cv_aoe']:.2f} / {r['cv_foe']:.2f}"
        if "aoe" in r:
            minutes = ", ".join("?" if t is None else f"{t / 60:.0f}" for t in r["train_time_s"])
            kde = f" {r['kde_nll']:.2f} |" if gaussian else ""
            release = ("-" if r["release_spread"] is None
                       else "{:.3f} / {:.3f}".format(*r["release_spread"]))
            lines.append(
                f"| {r['scene']} | {r['aoe']:.3f} ± {r['aoe_spread']:.3f} | "
                f"{r['foe']:.3f} ± {r['foe_spread']:.3f} | {release} | {paper}{kde} {cv} | "
                f"{', '.join(map(str, r['seeds']))} | {minutes} min | `{r['command']}` |")
        else:
            progress = "".join(f" (seed {seed} at epoch {epoch} of {epochs})"
                               for seed, epoch in r.get("in_progress", {}).items())
            lines.append(f"| {r['scene']} | missing{progress} | missing | - | {paper}"
                         f"{' - |' if gaussian else ''}"
                         f" {cv} | - | - | `{r['command']}` |")
    if len(rows) == len(ETH_UCY_SCENES):
        mean = lambda k: sum(r[k] for r in rows) / len(rows)
        finished = all("aoe" in r for r in rows)
        ours = f"{mean('aoe'):.3f} | {mean('foe'):.3f}" if finished else "- | -"
        kde = ((f" {mean('kde_nll'):.2f} (paper -1.98) |" if finished else " - |") if gaussian
               else "")
        lines.append(f"| AVG | {ours} | | {mean('paper_aoe'):.2f} | {mean('paper_foe'):.2f} |{kde} "
                     f"{mean('cv_aoe'):.2f} / {mean('cv_foe'):.2f} | | | |")
        if not finished:
            lines += ["", "No average of ours: not every scene has a finished run."]
    trained_by = [f"{r['scene']} {seed}: {', '.join(run['code']) if run.get('code') else 'before'}"
                  for r in rows for seed, run in r.get("per_seed", {}).items()]
    if trained_by:
        lines += ["", "Code that trained each run (git commit; 'before': trained before commits "
                  "were recorded, i.e. before the release-faithful encoder initialisation and "
                  "attention dropout of commits f5608ec and d394412, docs/reproducing.md): "
                  + "; ".join(trained_by) + "."]
    for r in rows:
        for seed, run in r.get("per_seed", {}).items():
            if run["workdir"].startswith("gst_jax/pretrained/"):
                lines += ["", f"{r['scene']}, seed {seed}: the test metrics recorded with the "
                          f"shipped model `{run['workdir']}` (trained by the command in its row)."]
            if "note" in run:
                lines += ["", f"{r['scene']}, seed {seed}: {run['note']}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenes", nargs="+", default=list(ETH_UCY_SCENES),
                        choices=ETH_UCY_SCENES, help="scenes (default: all five)")
    parser.add_argument("--protocol", default="paper", choices=("paper", "loo"),
                        help="paper: the release's per-file split (Table I); loo: "
                             "leave-one-scene-out")
    parser.add_argument("--output", default="deterministic", choices=("deterministic", "gaussian"),
                        help="GST (D) or GST (P) (default: deterministic)")
    parser.add_argument("--epochs", type=int, default=200, help="epochs of the runs (default: 200)")
    parser.add_argument("--seeds", default="1000",
                        help="comma-separated training seeds (default: 1000, the paper's)")
    parser.add_argument("--train", action="store_true",
                        help="train (or resume) and evaluate the runs that have neither a final "
                             "evaluation under --runs nor a record in the output folder (a "
                             "shipped model does not count)")
    parser.add_argument("--checkpoint-every", type=int, default=5,
                        help="epochs between checkpoints of the runs --train starts or resumes "
                             "(default: 5)")
    parser.add_argument("--park", action="store_true",
                        help="copy the newest checkpoint of each unfinished run into --parked "
                             "(commit it to continue in another sitting)")
    parser.add_argument("--parked", type=Path, default=PARKED,
                        help=f"folder of parked runs (default: {PARKED})")
    add_results_flags(parser, "table1",
                      "table1[_loo][_p].md/.json/.png and the per-run records runs/*.json")
    args = parser.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    out = results_folder(args)
    records = out / "runs"
    if args.park:
        for scene in args.scenes:
            for seed in seeds:
                workdir = workdir_of(Path(args.runs), scene, args.protocol, args.output,
                                     args.epochs, seed)
                if not (records / f"{workdir.name}.json").exists() and (
                        epoch := park(workdir, args.parked / workdir.name)):
                    print(f"parked {workdir.name} after epoch {epoch}", file=sys.stderr)
        return

    rows = []
    for scene in args.scenes:
        per_seed = [r for seed in seeds if (r := run_scene_seed(
            Path(args.runs), records, scene, args.protocol, args.output, args.epochs, seed,
            args.train, args.checkpoint_every, args.parked, drop_parked=args.publish))]
        seed_shown = seeds[0] if len(seeds) == 1 else "SEED"
        command = " ".join(["python -m gst_jax.train", *train_flags(
            scene, args.protocol, args.output, args.epochs, seed_shown)])
        baseline = constant_velocity_baseline(
            data.load_split(DataConfig(scene=scene, protocol=args.protocol), "test"))
        in_progress = {} if per_seed else {seed: epoch for seed in seeds if (
            epoch := trained_epochs(Path(args.runs), args.parked, scene, args.protocol, args.output,
                                    args.epochs, seed)) is not None}
        rows.append(summarize(scene, args.output, per_seed, command, baseline, in_progress))
    stem = "table1" + ("_loo" if args.protocol == "loo" else "") + (
        "_p" if args.output == "gaussian" else "")
    out.mkdir(parents=True, exist_ok=True)
    table1_against_paper(rows, out / f"{stem}.png", title=(
        f"{'GST (P)' if args.output == 'gaussian' else 'GST (D)'}, {args.protocol} protocol, "
        f"n = 1, ghost, {args.epochs} epochs, test split, 20 runs"),
        paper_label="paper" if args.protocol == "paper" else "paper (its own split)")
    table = (markdown(rows, args.output, args.protocol, args.epochs)
             + f"\n![ours, the paper and constant velocity per scene]({stem}.png)\n")
    (out / f"{stem}.md").write_text(table)
    (out / f"{stem}.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(json.dumps(rows, indent=2) if args.json else table)
    print(f"written: {out / stem}.md, .json", file=sys.stderr)


if __name__ == "__main__":
    main()
