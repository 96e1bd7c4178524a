"""The comparative study as separate runs, and the paper's three claims judged on it.

With `experiments/sweep_all.py --layout runs`, each member (n, detection, seed) trains as its
own run (`python -m gst_jax.train`, then `python -m gst_jax.evaluate`) in
<workdir>/<scene>/n<N>-<partial|full>-seed<S>, several at once, each process on a core of its
own. `--publish` records each finished member's evaluation as
results/runs/study-<scene>-n<N>-<mode>-seed<S>-e<epochs>.json; from then on that record
counts as a finished member, so a fresh clone tabulates the study without its runs.

The claims, each judged on paired differences where lower favours the paper:
  partial  - the test AOE of a member observing everyone minus the same n and seed observing
             the fully detected pedestrians only (Fig. 4);
  sparse   - a sparse member's AOE minus full connection's, same detection and seed (Fig. 6);
  freezing - a sparse member's rate of freezing or turning back minus full connection's on the
             same random encounters (experiments/encounters.py; Fig. 5(d)).
"""

from __future__ import annotations

import contextlib
import datetime
import json
import os
import queue
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Sequence

import numpy as np

import _common
from gst_jax.config import Member
from gst_jax.figures import n_label

CLAIMS = {
    "partial": "Observing the partially detected pedestrians too predicts better than "
               "observing the fully detected ones only (Fig. 4)",
    "sparse": "A sparse interaction graph (n of them) predicts better than full connection "
              "(Fig. 6)",
    "freezing": "Sparsity keeps the robot from freezing or turning back in front of a group "
                "(Fig. 5(d))",
}
# A claim holds when at least this share of its paired differences favours it and the mean
# over seeds of every (scene, n, detection) does; it does not hold when as many oppose it.
# Fixed before the study's second and third seeds were in.
AGREEING_SHARE = 2 / 3


# --- Members as runs ----------------------------------------------------------------------

def evaluation_file(workdir: Path, scene: str, protocol: str, epochs: int) -> Path:
    """Where `python -m gst_jax.evaluate` writes a member's test evaluation."""
    return workdir / "eval" / f"{scene}-{protocol}-test-e{epochs}.json"


def record_file(scene: str, member: Member, epochs: int) -> Path:
    """A member's published evaluation record in results/runs/."""
    return _common.RESULTS / "runs" / f"study-{scene}-{member.name}-e{epochs}.json"


def parked_copy(parked: Path, scene: str, member: Member, epochs: int) -> Path:
    """Where `sweep_all.py --park` keeps an unfinished member's newest checkpoint."""
    return parked / f"study-{scene}-{member.name}-e{epochs}"


def encounter_label(member: Member) -> str:
    """The member's name in experiments/encounters.py's record: 'n=F partial 1000'."""
    return f"n={member.edge_heads or 'F'} {member.detection} {member.seed}"


def finished_members(members: Sequence[Member], scene: str, protocol: str, epochs: int,
                     folder: Path, published: bool) -> dict[Member, dict]:
    """The members with a test evaluation after `epochs`: in their work directory under
    `folder`, or (`published`) recorded in results/runs/."""
    found = {}
    for member in members:
        for path in [evaluation_file(folder / member.name, scene, protocol, epochs)] + (
                [record_file(scene, member, epochs)] if published else []):
            if path.is_file():
                record = json.loads(path.read_text())
                if record.get("protocol_name", protocol) == protocol:
                    found[member] = record
                    break
    return found


def member_commands(member: Member, scene: str, protocol: str, epochs: int, schedule: str,
                    eval_samples: int, max_train_windows: int, workdir: Path) -> list[list[str]]:
    """The two commands that train (or resume) and evaluate one member."""
    train = [sys.executable, "-u", "-m", "gst_jax.train", "--scene", scene,
             "--protocol", protocol, "--edge-heads", str(member.edge_heads),
             "--seed", str(member.seed), "--epochs", str(epochs), "--schedule", schedule,
             "--workdir", str(workdir)]
    if member.fully_detected_only:
        train.append("--fully-detected-only")
    if max_train_windows:
        train += ["--max-train-windows", str(max_train_windows)]
    evaluate = [sys.executable, "-u", "-m", "gst_jax.evaluate", str(workdir),
                "--samples", str(eval_samples)]
    return [train, evaluate]


def train_members(members: Sequence[Member], scene: str, folder: Path, workers: int,
                  **settings) -> list[str]:
    """Train and evaluate each member, `workers` at once (each process pinned to a core of
    its own where the system allows), its output in <folder>/<member>.log; a stopped member
    resumes from its last checkpoint when run again. Returns the members that failed."""
    folder.mkdir(parents=True, exist_ok=True)
    free_cores: queue.Queue = queue.Queue()
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    for slot in range(workers):
        free_cores.put(cores[slot % len(cores)] if workers > 1 and cores else None)
    done: list[str] = []
    failed: list[str] = []
    study_started = time.time()

    def run(member: Member) -> None:
        core = free_cores.get()
        started = time.time()
        print(f"{scene} {member.name}: training" + (f" on core {core}" if core is not None
                                                     else "")
              + f", log {folder / member.name}.log", flush=True)
        try:
            with open(folder / f"{member.name}.log", "a") as log:
                for command in member_commands(member, scene, workdir=folder / member.name,
                                               **settings):
                    process = subprocess.Popen(command, stdout=log, stderr=log)
                    if core is not None:    # pinned from here (no preexec_fn: threads)
                        with contextlib.suppress(ProcessLookupError):    # ended already
                            os.sched_setaffinity(process.pid, {core})
                    if process.wait():
                        failed.append(member.name)
                        break
        finally:
            free_cores.put(core)
        done.append(member.name)
        # Members finish at the pace so far (the workers included); larger n cost more.
        to_go = (time.time() - study_started) / len(done) * (len(members) - len(done))
        print(f"{scene} {member.name}: {'failed' if member.name in failed else 'finished'} "
              f"after {time.time() - started:.0f} s ({len(done)} of {len(members)}, about "
              f"{datetime.timedelta(seconds=round(to_go))} to go at this pace)", flush=True)

    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(run, members))
    return failed


# --- The claims -----------------------------------------------------------------------------

def paired_differences(all_results: Sequence[dict], encounters: dict | None
                       ) -> dict[str, list[dict]]:
    """Per claim, its paired differences (lower favours the paper), each with its scene, n,
    detection (None: both modes are the pair) and seed."""
    differences: dict[str, list[dict]] = {claim: [] for claim in CLAIMS}
    for results in all_results:
        scene = results["scene"]
        by = {(m["edge_heads"], m["fully_detected_only"], m["seed"]): m
              for m in results["members"]}
        for (n, fully, seed), member in sorted(by.items()):
            mode = "full" if fully else "partial"
            pairs = [("partial", None, by.get((n, True, seed)))] if not fully else []
            if n:
                pairs.append(("sparse", mode, by.get((0, fully, seed))))
            for claim, detection, other in pairs:
                if other:
                    differences[claim].append({
                        "scene": scene, "edge_heads": n, "detection": detection, "seed": seed,
                        "aoe": member["aoe"] - other["aoe"], "foe": member["foe"] - other["foe"]})
    for pair in (encounters or {}).get("pairs", []):
        n, mode, seed = pair["sparse"].split()          # 'n=1 partial 1000'
        value, low, high = pair["freezing_difference"]
        differences["freezing"].append({
            "scene": encounters.get("scene", "?"), "edge_heads": int(n[2:]), "detection": mode,
            "seed": int(seed), "freezing": value, "interval": [low, high]})
    return differences


def verdict(differences: Sequence[dict], key: str) -> dict:
    """holds / does not hold / mixed (see AGREEING_SHARE), with the counts it rests on."""
    groups: dict[tuple, list[float]] = {}
    for d in differences:
        groups.setdefault((d["scene"], d["edge_heads"], d["detection"]), []).append(d[key])
    values = [d[key] for d in differences]
    favour, oppose = sum(v < 0 for v in values), sum(v > 0 for v in values)
    means = {group: float(np.mean(v)) for group, v in sorted(groups.items())}
    agreeing = {group: sum(x < 0 for x in v) for group, v in groups.items()}
    if not values:
        judged = "not measured"
    elif favour >= AGREEING_SHARE * len(values) and all(m < 0 for m in means.values()):
        judged = "holds"
    elif oppose >= AGREEING_SHARE * len(values) and all(m > 0 for m in means.values()):
        judged = "does not hold"
    else:
        judged = "mixed"
    return {"verdict": judged, "pairs": len(values), "favour": favour, "oppose": oppose,
            "means": [{"scene": s, "edge_heads": n, "detection": d, "mean": m,
                       "seeds": len(groups[(s, n, d)]), "favour": agreeing[(s, n, d)]}
                      for (s, n, d), m in means.items()]}


def judge_claims(all_results: Sequence[dict], encounters: dict | None) -> dict:
    """Every claim's verdict (AOE for the prediction claims, FOE counted beside), its paired
    differences and constant velocity on the same data."""
    differences = paired_differences(all_results, encounters)
    claims = {}
    for claim, text in CLAIMS.items():
        key = "freezing" if claim == "freezing" else "aoe"
        claims[claim] = {"claim": text, **verdict(differences[claim], key),
                         "differences": differences[claim]}
        if key == "aoe":
            claims[claim]["foe_favour"] = sum(d["foe"] < 0 for d in differences[claim])
    constant_velocity: dict = {"scenes": {r["scene"]: {"aoe": r["table"][0]["cv_aoe"],
                                                       "foe": r["table"][0]["cv_foe"]}
                                          for r in all_results}}
    if encounters:
        rates = encounters["models"]["constant velocity"]
        constant_velocity["encounters"] = {key: rates[key][0]
                                           for key in ("freezing_or_u_turn", "collided")}
    return {"claims": claims, "constant_velocity": constant_velocity}


def format_claims(judged: dict) -> str:
    """The claims table and the paired differences behind it, as markdown."""
    def group_name(d):
        return (f"{d['scene']} n={n_label(d['edge_heads'])}"
                + (f" {d['detection']}" if d["detection"] else ""))

    cv = judged["constant_velocity"]
    lines = ["## The paper's claims", "",
             "Paired differences, lower favouring the paper: claims 1 and 2 on the test AOE of "
             "two members trained with the same seed (FOE counted beside), claim 3 on the "
             "freezing rates of two members on the same encounters. A claim holds when at "
             "least two thirds of its pairs and the mean over seeds of every "
             "(scene, n, detection) favour it, does not hold when as many oppose it, and is "
             "mixed otherwise.", "",
             "| claim | pairs favouring it | mean over seeds (seeds favouring it) | verdict |",
             "|---|---|---|---|"]
    for number, claim in enumerate(judged["claims"].values(), 1):
        favour = f"{claim['favour']} of {claim['pairs']}"
        if "foe_favour" in claim:
            favour = f"AOE {favour}; FOE {claim['foe_favour']} of {claim['pairs']}"
        means = "; ".join(f"{group_name(m)} {m['mean']:+.3f} ({m['favour']} of {m['seeds']})"
                          for m in claim["means"])
        lines.append(f"| {number}. {claim['claim']} | {favour} | {means or '-'} | "
                     f"**{claim['verdict']}** |")
    lines += ["", "Constant velocity on the same pedestrians: " + "; ".join(
        f"{scene} AOE {v['aoe']:.3f} / FOE {v['foe']:.3f}" for scene, v in cv["scenes"].items())
        + "."]
    if "encounters" in cv:
        lines[-1] += (f" On the same encounters it froze or turned back in "
                      f"{cv['encounters']['freezing_or_u_turn']:.3f} of them and collided in "
                      f"{cv['encounters']['collided']:.3f}.")
    lines += ["", "| claim | pair | seed | difference |", "|---|---|---|---|"]
    for number, claim in enumerate(judged["claims"].values(), 1):
        for d in claim["differences"]:
            if "freezing" in d:
                low, high = d["interval"]
                value = f"{d['freezing']:+.3f} [{low:+.3f}, {high:+.3f}]"
            else:
                value = f"AOE {d['aoe']:+.3f}, FOE {d['foe']:+.3f} m"
            lines.append(f"| {number} | {group_name(d)} | {d['seed']} | {value} |")
    return "\n".join(lines) + "\n"
