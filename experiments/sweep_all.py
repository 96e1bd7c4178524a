"""The comparative study across datasets (paper Figs. 4-6) and the paper's claims judged on it.

    python experiments/sweep_all.py --scenes zara1 hotel --epochs 20 --seeds 3 \
        --workdir runs/sweep_all
    python experiments/sweep_all.py --scenes eth --edge-heads 0,1,4,16 --layout runs \
        --workers 2 --workdir runs/study --publish

--layout sweep (the default) trains each scene's members in one program, <workdir>/<scene>/
(resumable); --layout runs trains each member as its own run, --workers at once, in
<workdir>/<scene>/<member>/ (experiments/_study.py; --tabulate trains nothing and tabulates
the members already evaluated). Either writes the study's tables (study.md, study.json) and
figures to <workdir>, or with --publish to results/, with the members' records in
results/runs/ (runs layout only). --epochs is the budget: tau anneals 0.5 -> 0.03 over it, so
a short budget is a short training, not a truncated 200-epoch one; the learning rate decays
every 50 epochs as in the release (`--schedule paper`) or every epochs/4 (`--schedule
compressed`, results/schedules.md). The claims count the freezing robot from --encounters
(experiments/encounters.py's record) when it exists.

A study longer than one sitting continues in the next one: `--park` copies the newest
checkpoint of every unfinished member, and of every finished one that the encounter record
lacks, into <parked>/study-<scene>-<member>-e<epochs>/, to be committed; the runs layout on a
machine without the member's work directory restores it from that copy (and resumes it if
unfinished), and with --publish the copy is deleted once the member's record is in
results/runs/.
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import _common
from _figures import (
    best_n_per_dataset,
    errors_against_n_per_seed,
    paired_gains,
    sparse_gain_against_density,
)
from _study import (
    encounter_label,
    evaluation_file,
    finished_members,
    format_claims,
    judge_claims,
    parked_copy,
    record_file,
    train_members,
)
from gst_jax import cli, data
from gst_jax.config import CROWD_SCENES, DETECTION, SCHEDULES, DataConfig, ModelConfig, TrainConfig
from gst_jax.training.members import plan_members, sweep_model_config
from gst_jax.training.sweep import fit_sweep, format_markdown, summarize


def main(argv: list[str] | None = None) -> None:
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
    parser.add_argument("--layout", choices=("sweep", "runs"), default="sweep",
                        help="sweep: a scene's members in one program; runs: each member its "
                             "own run (default: sweep)")
    parser.add_argument("--workers", type=cli.positive_int, default=1,
                        help="runs layout: members trained at once, a core each (default: 1)")
    parser.add_argument("--tabulate", action="store_true",
                        help="runs layout: train nothing, tabulate the evaluated members")
    parser.add_argument("--park", action="store_true",
                        help="runs layout: train nothing, copy the newest checkpoint of each "
                             "unfinished member, and of each finished one that --encounters "
                             "lacks, into --parked (commit it to continue in another sitting)")
    parser.add_argument("--parked", type=Path, default=_common.PARKED,
                        help=f"folder of parked members (default: {_common.PARKED})")
    parser.add_argument("--encounters", type=Path, default=None,
                        help="experiments/encounters.py's record, for the freezing claim "
                             "(default: results/encounters.json)")
    parser.add_argument("--max-train-windows", type=int, default=0, help="smoke tests only")
    parser.add_argument("--max-eval-windows", type=int, default=0, help="smoke tests only")
    parser.add_argument("--workdir", type=Path, default=Path("runs/sweep_all"),
                        help="where the members train and the tables go (default: runs/sweep_all)")
    parser.add_argument("--publish", action="store_true",
                        help="runs layout: write the tables, figures and members' records into "
                             "results/ (a record there counts as a finished member)")
    args = parser.parse_args(argv)
    if args.layout == "sweep" and (args.publish or args.tabulate or args.park):
        parser.error("--publish, --tabulate and --park need --layout runs")

    members = plan_members(args.edge_heads, args.fully_detected_only,
                           [args.seed + i for i in range(args.seeds)])
    train_config = TrainConfig(epochs=args.epochs, seed=args.seed, schedule=args.schedule,
                               max_train_windows=args.max_train_windows)
    if args.park:
        for scene in args.scenes:
            park_members(args, scene, members)
        return
    all_results = []
    for scene in args.scenes:
        print(f"== {scene}", flush=True)
        data_config = DataConfig(scene=scene, protocol=args.protocol)
        if args.layout == "sweep":
            all_results.append(fit_sweep(
                sweep_model_config(ModelConfig(), members), data_config, train_config, members,
                args.workdir / scene, eval_samples=args.eval_samples,
                max_eval_windows=args.max_eval_windows))
        elif results := tabulate_runs(args, scene, data_config, train_config, members):
            all_results.append(results)
    if not all_results:
        raise SystemExit("no member has finished: nothing to tabulate")
    write_study(all_results, judge_claims(all_results, read_encounters(args) or None),
                _common.RESULTS if args.publish else args.workdir)


def tabulate_runs(args, scene: str, data_config: DataConfig, train_config: TrainConfig,
                  members) -> dict | None:
    """Train the scene's unfinished members as runs (unless --tabulate), then summarize the
    evaluated ones as a sweep's results (None: none evaluated yet)."""
    folder = args.workdir / scene

    def finished():
        return finished_members(members, scene, args.protocol, args.epochs, folder,
                                published=args.publish)

    for member in members:
        parked = parked_copy(args.parked, scene, member, args.epochs)
        if parked.is_dir() and not (folder / member.name / "checkpoints").is_dir():
            shutil.copytree(parked, folder / member.name, dirs_exist_ok=True)  # another sitting's
    if not args.tabulate:
        done = finished()
        waiting = [m for m in members if m not in done]
        failed = train_members(waiting, scene, folder, args.workers, protocol=args.protocol,
                               epochs=args.epochs, schedule=args.schedule,
                               eval_samples=args.eval_samples,
                               max_train_windows=args.max_train_windows)
        if failed:
            print(f"{scene}: failed, see their logs in {folder}: {', '.join(failed)}")
    records = finished()
    if not records:
        return None
    if args.publish:
        for member in records:
            if not record_file(scene, member, args.epochs).is_file():
                shutil.copy2(evaluation_file(folder / member.name, scene, args.protocol,
                                             args.epochs), record_file(scene, member, args.epochs))
            shutil.rmtree(parked_copy(args.parked, scene, member, args.epochs),
                          ignore_errors=True)
    evaluated = [m for m in members if m in records]
    test_set = data.load_split(data_config, "test", ModelConfig().grid)
    results = summarize([records[m] for m in evaluated], evaluated, data_config, train_config,
                        args.eval_samples, test_set)
    return {**results, "waiting": [m.name for m in members if m not in records]}


def park_members(args, scene: str, members) -> None:
    """Copy the newest checkpoint of each of the scene's unfinished members, and of each
    finished one that the encounter record lacks (experiments/encounters.py simulates it), to
    --parked."""
    folder = args.workdir / scene
    done = finished_members(members, scene, args.protocol, args.epochs, folder,
                            published=args.publish)
    encountered = read_encounters(args)
    simulated = (encountered.get("members", []) if encountered.get("scene") == scene else [])
    for member in members:
        if member in done and encounter_label(member) in simulated:
            continue
        if epoch := _common.park(folder / member.name,
                                 parked_copy(args.parked, scene, member, args.epochs)):
            print(f"parked {scene} {member.name} after epoch {epoch}"
                  + (" (finished, for its encounters)" if member in done else ""), flush=True)


def read_encounters(args) -> dict:
    """experiments/encounters.py's record (--encounters), {} when there is none."""
    path = args.encounters or _common.RESULTS / "encounters.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def write_study(all_results: list[dict], judged: dict, out: Path) -> None:
    """study.json, study.md and the figures in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    figures = {"study_fig4_errors_vs_n.png": errors_against_n_per_seed(
        all_results, out / "study_fig4_errors_vs_n.png")}
    differences = {claim: v["differences"] for claim, v in judged["claims"].items()}
    if any(differences.values()):     # none before a pair of members has finished
        figures["study_fig6_paired_gains.png"] = paired_gains(
            differences, out / "study_fig6_paired_gains.png")
    if len(all_results) > 1:          # across datasets: gains against density, best n
        figures["study_sparse_gain_vs_density.png"] = sparse_gain_against_density(
            all_results, out / "study_sparse_gain_vs_density.png")
        figures["study_best_n.png"] = best_n_per_dataset(all_results, out / "study_best_n.png")
    (out / "study.json").write_text(json.dumps({"scenes": all_results, **judged}, indent=1)
                                    + "\n")
    header = ["# The comparative study (paper Figs. 4-6) and the paper's claims", "",
              "Made by experiments/sweep_all.py as docs/reproducing.md (\"The comparative "
              "study\") says."]
    for results in all_results:
        if results.get("waiting"):     # a study of runs that have not all finished
            header.append(f"{results['scene']}: {len(results['members'])} members evaluated, "
                          f"{len(results['waiting'])} waiting ({', '.join(results['waiting'])}).")
    sections = (["\n".join(header + [""])]
                + [format_markdown(r, "## Scene") for r in all_results]
                + [format_claims(judged), "\n".join(f"![{name}]({name})" for name in figures)])
    markdown = "\n".join(sections) + "\n"
    (out / "study.md").write_text(markdown)
    print(markdown)
    print(f"written in {out}: study.json, study.md, " + ", ".join(figures))


if __name__ == "__main__":
    main()
