"""Navigation records (`gst_jax.simulate.crowdnav.navigation.evaluate` writes one per run):
their file names, their rows of results/navigation.md's table, and the paired comparison of
records that played the same episodes.

    name = record_name("mpc", "dtaci", "orca", 500, 1000)   # mpc-dtaci-episodes500-seed1000
    print(summary(record, out))       # its row, and its differences from out's other records
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gst_jax.paired import paired_means, paired_rates
from gst_jax.simulate.crowdnav.environment import NO_SHIFT

# What --regions takes: conformal discs, none, or a margin calibrated online.
DECISION = "decision"
REGIONS = ("dtaci", "aci", "none", DECISION)


# The measures of a table's columns, as results/navigation.md shows them.
COLUMNS = ("success", "collision", "timeout", "navigation_time_s", "path_length_m",
           "intrusion_ratio", "mean_radius_m")


def row_label(record: dict) -> str:
    """A record's first four cells: planner, predictions, discs, humans (ORCA's where it
    names none, as records before the social-force option; then how many where not 20,
    whether they react to the robot, and their shift)."""
    model = record.get("model") or ""
    predictions = {"cv-mpc": "constant velocity", "standing-mpc": "none (standing)",
                   "truth-mpc": "truth (the simulator's)"}.get(
        record["planner"], f"GST ({model_name(model)})")
    adapted = record.get("adaptation", "none")
    predictions += f", {adapted}" if adapted != "none" else ""
    predictions += ", fresh tracks" if record.get("fresh_tracks") else ""
    method = {"dtaci": "DtACI", "aci": "ACI"}.get(record["regions"], record["regions"])
    discs = {"none": "none", DECISION: "calibrated margin"}.get(
        record["regions"], f"{method} {record['alpha']:g}")
    humans = "social force" if record.get("humans") == "social-force" else "ORCA"
    humans = ", ".join([humans, *([f"{record['num_humans']} of them"]
                                  if record.get("num_humans", 20) != 20 else []),
                        *(["reactive"] if record.get("reactive") else []),
                        *([f"shift: {record['shift']}"] if record.get("shift", NO_SHIFT)
                          != NO_SHIFT else [])])
    return f"sampling MPC | {predictions} | {discs} | {humans}"


def format_table(rows: list[dict]) -> str:
    """Records as results/navigation.md's table: a row per record, labelled by its "label"
    (`row_label`'s cells), the measures to three decimals (blank where missing)."""
    lines = ["| planner | predictions | discs | humans | " + " | ".join(COLUMNS) + " |",
             "|---" * (4 + len(COLUMNS)) + "|"]
    for row in rows:
        cells = [f"{row[c]:.3f}" if isinstance(row.get(c), float) else "" for c in COLUMNS]
        lines.append(f"| {row['label']} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def summary(result: dict, out: Path | None = None) -> str:
    """An evaluation's record as `python -m gst_jax.navigate evaluate` prints it: its row of
    results/navigation.md's table, its episodes, seed and seconds, and, with `out`, its paired
    differences from the other records there of the same episodes (`paired_lines`)."""
    return "\n".join([format_table([{**result, "label": row_label(result)}]),
                      f"{result['episodes']} episodes of seed {result['seed']}; compiling "
                      f"{result['compile_s']} s, running {result['run_s']} s",
                      *(paired_lines(result, same_episodes(result, out)) if out else [])])


# What makes two records' episodes the same ones.
EPISODES_OF = ("humans", "reactive", "num_humans", "shift", "seed", "episodes")


def same_episodes(record: dict, out: Path) -> list[dict]:
    """The other records in `out` that played `record`'s episodes (EPISODES_OF) and kept
    them one by one (per_episode)."""
    found = []
    for path in sorted(out.glob("*.json")):
        try:
            other = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        same = isinstance(other, dict) and "per_episode" in other and all(
            other.get(k) == record.get(k) for k in EPISODES_OF)
        setting_of = lambda r: (r["planner"], r["regions"], r.get("alpha"), r.get("model"),
                                r.get("adaptation", "none"), r.get("fresh_tracks", False))
        if same and setting_of(other) != setting_of(record):
            found.append(other)
    return found


def compare(a: dict, b: dict) -> dict:
    """Record a minus record b over their episodes, paired: success and collision rates
    (difference, 95 % interval, McNemar's p) and the mean intrusion ratio."""
    outcomes = lambda record, kind: np.array(record["per_episode"]["outcome"]) == kind
    return {"success": paired_rates(outcomes(a, "success"), outcomes(b, "success")),
            "collision": paired_rates(outcomes(a, "collision"), outcomes(b, "collision")),
            "intrusion_ratio": paired_means(a["per_episode"]["intrusion_ratio"],
                                            b["per_episode"]["intrusion_ratio"])}


def setting(record: dict) -> str:
    """A record's predictor and discs, as paired comparisons name them: e.g. "cv + DtACI"."""
    discs = {"none": "no discs", "dtaci": "DtACI", "aci": "ACI",
             DECISION: "calibrated margin"}[record["regions"]]
    model = record.get("model")
    named = f" ({model_name(model)})" if model not in (None, DEFAULT_MODEL) else ""
    adapted = record.get("adaptation", "none")
    return (f"{record['predictor']}{named}" + (f" + {adapted}" if adapted != "none" else "")
            + f" + {discs}" + (" (fresh tracks)" if record.get("fresh_tracks") else ""))


def paired_lines(record: dict, others: list[dict]) -> list[str]:
    """`record` against each of `others` (same episodes): success difference with its 95 %
    paired-bootstrap interval, McNemar's exact p and the discordant episodes."""
    if not others:
        return []
    lines = [f"paired with the other settings of these {record['episodes']} episodes (95 % "
             "paired-bootstrap interval; McNemar's exact p; episodes only this one / only the "
             "other succeeded in):"]
    for other in others:
        success = compare(record, other)["success"]
        lines.append(f"  success - {setting(other)}: {success['difference']:+.3f} "
                     f"({success['low']:+.3f} to {success['high']:+.3f}), p {success['p']:.3g} "
                     f"({success['only_a']} / {success['only_b']})")
    return lines


def record_name(planner: str, regions: str, humans: str, episodes: int, seed: int,
                reactive: bool = False, num_humans: int = 20, shift: str = NO_SHIFT,
                model: str | None = None, adaptation: str = "none",
                fresh_tracks: bool = False) -> str:
    """The stem of an evaluation's files: PLANNER-REGIONS[-HUMANS][-reactive][-humansN]
    [-shiftS][-modelNAME][-adaptNAME][-freshtracks]-episodesCOUNT-seedSEED (the defaults
    unnamed: 20 ORCA humans who ignore the robot, no shift, GST's model DEFAULT_MODEL, no
    adaptation, CrowdNav++'s tracks), so that
    runs of other settings and lengths sit beside it."""
    return "-".join([planner, regions, *([humans] if humans != "orca" else []),
                     *(["reactive"] if reactive else []),
                     *([f"humans{num_humans}"] if num_humans != 20 else []),
                     *([f"shift{shift}"] if shift != NO_SHIFT else []),
                     *([f"model{model_name(model)}"] if model not in (None, DEFAULT_MODEL)
                       else []),
                     *([f"adapt{adaptation}"] if adaptation != "none" else []),
                     *(["freshtracks"] if fresh_tracks else []),
                     f"episodes{episodes}", f"seed{seed}"])


# GST's model where a record names none: the one the study was first run with.
DEFAULT_MODEL = "pretrained:crowdnav_sj_rand"


def model_name(model: str) -> str:
    """A model as records and tables name it: pretrained:NAME's NAME, a run's folder name."""
    return model.removeprefix("pretrained:").rstrip("/").split("/")[-1]
