"""Coverage of conformal regions around streamed predictions, scene by scene and under shift:

    python experiments/conformal_coverage.py                # runs/conformal_coverage/
    python experiments/conformal_coverage.py --publish      # results/conformal_coverage.md
    python experiments/conformal_coverage.py --joint        # whole-horizon: conformal_joint.md

Each case plays a stream through the model once (`gst_jax.coverage.record`, as
`python -m gst_jax.conformal` does) and measures split conformal (calibrated on the first 30 %
of the frames), ACI and DtACI (pooled per horizon step, their default settings) at
alpha = 0.1 on the frames after those 30 %, the same predictions (mean mode) for every
method:

- each ETH/UCY scene's test split (the paper protocol's last 20 % of its files) through the
  scene's shipped model (`pretrained:<scene>_d`);
- shift between scenes: HOTEL's model on ETH's test split;
- shift in time: the navigation task's own humans (`gst_jax.simulate.crowdnav`: 20 ORCA
  humans who do not see the robot, no shift, recorded as `navigate crowds` records them, one
  episode of 150 s at 0.25 s from seed 900) played at every step for its first 50 s and at
  every second step after, so that everyone walks twice as fast from the middle of the
  stream's 400 frames on, through `pretrained:crowdnav_sim` (CrowdNav++'s architecture trained
  on ORCA-like crowds at their own speed, those of a stand-in simulator since removed). Split
  conformal is calibrated before the change.

ACI's step (gamma = 0.005 per score, `conformal.aci`'s default) was chosen on validation
streams, never on these: `--select` plays each scene's validation split (protocol paper-val,
the end of each file's training part) through the same model and tabulates ACI's coverage
error for each gamma and batch mode (<out>/conformal_selection.md).

Every (case, method) is recorded in <out>/runs/conformal-<case>-<method>.json as it finishes, and
skipped when its record exists, so an interrupted run continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Callable

import numpy as np

from _common import add_results_flags, results_folder
from gst_jax.config import DataConfig
from gst_jax.coverage import (
    FrameRows,
    exchangeable_coverage,
    measure,
    record,
    scene_streams,
    simultaneous,
)
from gst_jax.progress import Progress, hms
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.crowds import Condition, person_ids, record_episodes
from gst_jax.simulate.crowdnav.environment import EnvParams

SCENES = ("eth", "hotel", "univ", "zara1", "zara2")
METHODS = ("split", "aci", "dtaci")     # the published table's (gst_jax.coverage has pid too)
ALPHA, CALIBRATION = 0.1, 0.3
# Within this of 1 - alpha at every horizon step: the criterion without shift, and
# with shift.
TOLERANCE, SHIFT_TOLERANCE = 0.01, 0.015


def speed_doubling_crowd(seed: int = 900, duration_s: float = 150.0) -> list[FrameRows]:
    """The frames of one episode of the task's ORCA humans (`duration_s` from its reset, what
    the robot detected, a human replaced at its goal under a new id): every step of its first
    third, every second step after (as many frames), so that the speed doubles halfway
    through the stream."""
    record = record_episodes(Condition(), 1, seed, steps=round(duration_s / EnvParams().step_s))
    positions, detected = record["positions"][0], record["detected"][0]
    ids = person_ids(record["replaced"][0])
    third = len(positions) // 3
    steps = list(range(third)) + list(range(third, len(positions), 2))
    return [(t, ids[t][detected[t]], positions[t][detected[t]]) for t in steps]


def cases() -> dict[str, tuple[str, Callable, str]]:
    """name: (model, its streams (a function: built when the case runs), what it shows)."""
    def scene(name):
        return lambda run: scene_streams(DataConfig(scene=name), "test", run.model_config.grid)
    table = {s: (f"pretrained:{s}_d", scene(s), "no shift") for s in SCENES}
    table["hotel-on-eth"] = ("pretrained:hotel_d", scene("eth"), "shift: another scene")
    table["speed-doubles"] = ("pretrained:crowdnav_sim", lambda run: [speed_doubling_crowd()],
                              "shift: speed x2 halfway")
    return table


def summary(name: str, shows: str, results: dict[str, dict]) -> dict:
    """One row: per method the worst horizon step's coverage gap and the mean radius."""
    tolerance = TOLERANCE if shows == "no shift" else SHIFT_TOLERANCE
    row = {"case": name, "shows": shows, "frames": results["split"]["frames"],
           "scores": sum(results["split"]["scores"])}
    for method, result in results.items():
        coverage = np.asarray(result["coverage"])
        row[method] = {"coverage_min": float(coverage.min()), "coverage_max": float(coverage.max()),
                       "within": bool(np.all(np.abs(coverage - (1 - ALPHA)) <= tolerance)),
                       "mean_radius": float(np.mean(result["radius"]))}
    row["dtaci_radius_over_split"] = row["dtaci"]["mean_radius"] / row["split"]["mean_radius"]
    return row


def markdown(rows: list[dict]) -> str:
    lines = ["# Conformal regions around streamed predictions", "",
             f"alpha = {ALPHA}; pooled per horizon step; mean-mode predictions; scored on the "
             f"frames after the first {CALIBRATION:.0%} (split conformal's calibration). Coverage: "
             "lowest-highest over the horizon steps; within: every step within "
             f"{TOLERANCE} of 0.9 ({SHIFT_TOLERANCE} under shift). Made by "
             "`python experiments/conformal_coverage.py --publish`.", "",
             "| case | frames | scores | " + " | ".join(
                 f"{m} coverage | {m} within | {m} radius (m)" for m in METHODS)
             + " | DtACI / split radius |",
             "|---|---|---|" + "---|---|---|" * len(METHODS) + "---|"]
    for row in rows:
        cells = [f"{row['case']} ({row['shows']})", str(row["frames"]), str(row["scores"])]
        for method in METHODS:
            m = row[method]
            cells += [f"{m['coverage_min']:.3f}-{m['coverage_max']:.3f}",
                      "yes" if m["within"] else "no", f"{m['mean_radius']:.2f}"]
        cells.append(f"{row['dtaci_radius_over_split']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def select(out: Path, progress: Progress) -> str:
    """ACI's gamma and batch mode, and PID's eta, k_i and c_sat, on the scenes' validation
    streams: per setting, the coverage error |coverage - 0.9| weighted by the scores of each
    (scene, horizon step), and how many (scene, step) cells land within TOLERANCE or issue
    infinite radii."""
    recordings = []
    for scene in SCENES:
        run = load_model(f"pretrained:{scene}_d")
        config = DataConfig(scene=scene, protocol="paper-val")
        recordings.append(record(run, scene_streams(config, "val", run.model_config.grid),
                                 calibration=CALIBRATION, progress=progress))
    lines = ["# The online methods' steps, chosen on the validation streams", "",
             f"alpha = {ALPHA}; each scene's validation split (protocol paper-val) through its "
             f"shipped model, scored after the first {CALIBRATION:.0%} of the frames; "
             f"{sum(r.frames for r in recordings)} frames in all. Made by "
             "`python experiments/conformal_coverage.py --select --publish`."]
    aci = [(("batch", b), ("gamma", g)) for b in ("sequential", "mean")
           for g in (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05)]
    pid = [(("eta", e), ("k_i", k), ("c_sat", c)) for e in (0.001, 0.005, 0.02)
           for k in (0.1, 1.0) for c in (1.0, 10.0, 100.0)]
    for method, settings in (("aci", aci), ("pid", pid)):
        names = [name for name, _ in settings[0]]
        lines += ["", f"## {method}", "", "| " + " | ".join(names) + " | weighted coverage "
                  f"error | cells within {TOLERANCE} | cells with infinite radii | mean radius "
                  "(m) |", "|" + "---|" * (len(names) + 4)]
        for options in settings:
            errors, counts, radii, infinite = [], [], [], 0
            for recording in recordings:
                result, _ = measure(recording, method, ALPHA, options=options)
                errors += [abs(c - (1 - ALPHA)) for c in result["coverage"]]
                counts += result["scores"]
                radii += result["radius"]
                infinite += int(np.isinf(result["radius"]).sum())
            errors, counts, radii = np.asarray(errors), np.asarray(counts), np.asarray(radii)
            lines.append("| " + " | ".join(str(v) for _, v in options) +
                         f" | {np.sum(errors * counts) / counts.sum():.4f} | "
                         f"{np.sum(errors <= TOLERANCE)}/{len(errors)} | {infinite} | "
                         f"{np.mean(radii):.2f} |")
    table = "\n".join(lines) + "\n"
    (out / "conformal_selection.md").write_text(table)
    return table


JOINT_TOLERANCE = 0.02          # the target: joint coverage 0.9 +- 0.02


def held_back() -> dict[str, tuple[str, Callable, str]]:
    """The scenes' validation streams (protocol paper-val: the end of each file's training
    part, before its test part) through the same models: data the method was not chosen on."""
    def scene(name):
        return lambda run: scene_streams(DataConfig(scene=name, protocol="paper-val"), "val",
                                         run.model_config.grid)
    return {f"{s} validation": (f"pretrained:{s}_d", scene(s), "held back") for s in SCENES}


def joint(out: Path, progress: Progress) -> str:
    """Whole-horizon coverage (all P steps inside their discs) of each case and of the held-back
    validation streams: per-step discs at alpha, Bonferroni's at alpha / P, and simultaneous
    discs (one score per prediction, `gst_jax.coverage.simultaneous`), for ACI and DtACI, with
    the mean radius over the steps; beside them, what the stream's length alone allows
    (`gst_jax.coverage.exchangeable_coverage`)."""
    lines = ["# Whole-horizon coverage: all predicted steps inside their discs", "",
             f"alpha = {ALPHA}; pooled; mean-mode predictions; the predictions made after the "
             f"first {CALIBRATION:.0%} of the frames whose every step was observed. Per step: "
             "each horizon step's discs at alpha; Bonferroni: at alpha / P; simultaneous: one "
             "score per prediction, the largest of its steps' errors over their scales, the "
             "scales and the method's start fixed on the first frames, then calibrated online. "
             "Cells: joint coverage / mean radius over the steps (m); within: simultaneous "
             f"within {JOINT_TOLERANCE} of 0.9. Made by "
             "`python experiments/conformal_coverage.py --joint --publish`.", "",
             "Exchangeable: the same stream with its frames in 2,000 random orders (each frame's "
             "predictions together, so nothing shifts) through split conformal, which is exactly "
             "valid there: the share of orders within 0.02 of 0.9 and the 95 % range, what the "
             "stream's length alone allows any method.", "",
             "| case | predictions | exchangeable: within / 95 % range | method | per step | "
             "Bonferroni | simultaneous | within |", "|---|---|---|---|---|---|---|---|"]
    rows = []
    for name, (model, streams_of, shows) in {**cases(), **held_back()}.items():
        run = load_model(model)
        recording = record(run, streams_of(run), calibration=CALIBRATION, progress=progress)
        spread = exchangeable_coverage(recording, ALPHA)
        allowed = {"within": float(np.mean(np.abs(spread - (1 - ALPHA)) <= JOINT_TOLERANCE)),
                   "range": np.quantile(spread, [0.025, 0.975]).tolist()}
        for method in ("aci", "dtaci"):
            per_step, _ = measure(recording, method, ALPHA)
            bonferroni, _ = measure(recording, method, ALPHA, bonferroni=True)
            together = simultaneous(recording, method, ALPHA)
            row = {"case": name, "shows": shows, "method": method,
                   "predictions": together["joint_predictions"], "exchangeable": allowed}
            for label, result in (("per_step", per_step), ("bonferroni", bonferroni),
                                  ("simultaneous", together)):
                row[label] = {"joint_coverage": result["joint_coverage"],
                              "mean_radius": float(np.mean(result["radius"]))}
            row["within"] = abs(together["joint_coverage"] - (1 - ALPHA)) <= JOINT_TOLERANCE
            rows.append(row)
            low, high = allowed["range"]
            lines.append(f"| {name} ({shows}) | {row['predictions']} | {allowed['within']:.2f} / "
                         f"{low:.3f}-{high:.3f} | {method} | " + " | ".join(
                f"{row[k]['joint_coverage']:.3f} / {row[k]['mean_radius']:.2f}"
                for k in ("per_step", "bonferroni", "simultaneous"))
                + f" | {'yes' if row['within'] else 'no'} |")
    within = [r for r in rows if r["within"]]
    lines += ["", f"Simultaneous discs within {JOINT_TOLERANCE} of 0.9: {len(within)} of "
              f"{len(rows)} (stream, method) cells; ACI {sum(r['method'] == 'aci' for r in within)}"
              f", DtACI {sum(r['method'] == 'dtaci' for r in within)} of {len(rows) // 2} each."]
    table = "\n".join(lines) + "\n"
    (out / "conformal_joint.md").write_text(table)
    (out / "conformal_joint.json").write_text(json.dumps(rows, indent=1) + "\n")
    return table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    table = cases()
    parser.add_argument("--cases", nargs="*", default=list(table), choices=list(table),
                        help="which cases (default: all)")
    add_results_flags(parser, "conformal_coverage", "conformal_coverage.md/.json and the "
                      "records runs/*.json", runs=False)
    parser.add_argument("--select", action="store_true", help="only tabulate ACI's and PID's "
                        "steps on the validation streams (conformal_selection.md)")
    parser.add_argument("--joint", action="store_true", help="only tabulate the whole-horizon "
                        "coverage of every case (conformal_joint.md)")
    args = parser.parse_args(argv)
    out = results_folder(args)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    rows, progress = [], Progress()
    if args.select or args.joint:
        print(select(out, progress) if args.select else joint(out, progress))
        return
    for name in args.cases:
        model, streams_of, shows = table[name]
        run, results, recording = load_model(model), {}, None
        for method in METHODS:
            path = out / "runs" / f"conformal-{name}-{method}.json"
            if not path.exists():
                if recording is None:                    # one pass of the model per case
                    started = time.perf_counter()
                    recording = record(run, streams_of(run), calibration=CALIBRATION,
                                       progress=progress)
                    progress.line(f"{name}: played in {hms(time.perf_counter() - started)}")
                result, _ = measure(recording, method, ALPHA)
                result.update(case=name, model=model)
                path.write_text(json.dumps(result, indent=1) + "\n")
            results[method] = json.loads(path.read_text())
        rows.append(summary(name, shows, results))
    (out / "conformal_coverage.json").write_text(json.dumps(rows, indent=1) + "\n")
    (out / "conformal_coverage.md").write_text(markdown(rows))
    print(json.dumps(rows, indent=1) if args.json else markdown(rows))


if __name__ == "__main__":
    main()
