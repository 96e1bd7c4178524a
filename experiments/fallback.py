"""Per person, GST or constant velocity? A rule on what a planner sees during the observation
(the closest other person, the people within 2 m), fixed on validation windows and reported
on the test splits beside GST and CV alone (issue 75, part 1):

    python experiments/fallback.py                    # runs/fallback/fallback.{md,json}
    python experiments/fallback.py --rule-models runs/paper-val --publish   # results/

Each ETH/UCY scene's shipped Table I model (`pretrained:<scene>_d`) on its paper test split,
20 samples (hard, tau 0.03), per-pedestrian errors as `gst_jax.strata` gives them (cached in
<out>/runs/). A rule keeps GST's prediction of a person where its feature lies on one side of
a threshold and takes constant velocity's elsewhere. The fallback is the candidate (GST
alone, CV alone or a rule) with the lowest mean over the scenes of the validation AOE: on the
validation windows of models trained under paper-val (`--rule-models`, held out for them),
or else on the shipped models' own (in-sample: they trained on them). The test splits are
read only to report it, beside the best rule where a predictor alone was chosen, with
paired 95 % intervals.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import NamedTuple, Union

import numpy as np

from _common import add_results_flags, results_folder
from gst_jax.progress import Progress
from gst_jax.strata import paired
from strata import SCENES, records_of

# Candidate rules: GST where a feature is "at least" or "below" a threshold.
THRESHOLDS = {"closest": (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0),
              "neighbours": (1, 2, 3, 4, 6)}
# Candidates too, so that a rule is chosen only where it beats both predictors alone.
GST_ALONE, CV_ALONE = "GST for everyone", "constant velocity for everyone"


class Rule(NamedTuple):
    """GST where `feature` (a record's `closest` or `neighbours`) is `gst_where` ("at least"
    or "below") `threshold`, constant velocity elsewhere."""

    feature: str
    gst_where: str
    threshold: float


Candidate = Union[Rule, str]          # a Rule, GST_ALONE or CV_ALONE


def keeps_gst(records: dict, rule: Candidate) -> np.ndarray:
    """Per pedestrian, whether the candidate takes GST's prediction."""
    if rule in (GST_ALONE, CV_ALONE):
        return np.full(records["model_ade"].shape, rule == GST_ALONE)
    value = records[rule.feature]
    return value >= rule.threshold if rule.gst_where == "at least" else value < rule.threshold


def chosen(records: dict, rule: Candidate) -> np.ndarray:
    """Per pedestrian, the ADE of the candidate's choice."""
    return np.where(keeps_gst(records, rule), records["model_ade"], records["cv_ade"])


def candidates() -> list[Candidate]:
    return [GST_ALONE, CV_ALONE] + [Rule(feature, side, t)
                                    for feature, thresholds in THRESHOLDS.items()
                                    for side in ("at least", "below") for t in thresholds]


def average(parts: dict, rule) -> tuple[float, dict]:
    per_scene = {scene: float(chosen(r, rule).mean()) for scene, r in parts.items()}
    return float(np.mean(list(per_scene.values()))), per_scene


def difference(parts: dict, rule, baseline: str) -> dict:
    """The rule's ADE less the baseline's (`cv_ade` or `model_ade`), paired per pedestrian:
    per scene and for the mean over the scenes, each with its 95 % interval (normal; the
    scenes' pedestrians are independent samples, so the mean's variance is the sum of the
    scenes' over their count squared)."""
    per_scene = {s: paired(chosen(r, rule) - r[baseline]) for s, r in parts.items()}
    mean = float(np.mean([d["mean"] for d in per_scene.values()]))
    half = float(np.sqrt(sum(((d["high"] - d["low"]) / 2) ** 2 for d in per_scene.values()))
                 / len(per_scene))
    return {"average": {"mean": mean, "low": mean - half, "high": mean + half}, **per_scene}


def rule_text(rule: Candidate) -> str:
    if isinstance(rule, str):
        return rule
    feature, side, threshold = rule
    what = {"closest": "the closest other person during the observation",
            "neighbours": "the most people within 2 m at one observed step"}[feature]
    unit = " m" if feature == "closest" else ""
    return f"GST where {what} is {side} {threshold:g}{unit}, constant velocity elsewhere"


def gst_share(records: dict, rule: Candidate) -> float:
    """The share of the pedestrians whose prediction the rule takes from GST."""
    return float(keeps_gst(records, rule).mean())


def choose(val: dict) -> tuple[Candidate, dict]:
    """The candidate with the lowest mean over `val`'s scenes of the AOE, and every
    candidate's mean. Candidates that tie there (they choose alike on every validation
    person) go to the one giving GST to the fewest validation people, then to the first
    listed."""
    scores = {rule: average(val, rule)[0] for rule in candidates()}
    share = {rule: np.mean([gst_share(r, rule) for r in val.values()]) for rule in scores}
    return min(scores, key=lambda rule: (scores[rule], share[rule])), scores


def _described(rule: Candidate) -> dict:
    return {**(rule._asdict() if isinstance(rule, Rule) else {}), "text": rule_text(rule)}


def held_out_models(folder: Path) -> dict[str, str]:
    """scene: the finished paper-val run folder/<scene>, for the scenes that have one."""
    return {s: str(folder / s) for s in SCENES if (folder / s / "summary.json").exists()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_results_flags(parser, "fallback", "fallback.md/.json and the cached records runs/",
                      runs=False)
    parser.add_argument("--rule-models", type=Path, metavar="DIR",
                        help="fix the rule on held-out validation windows: DIR/<scene> is a "
                             "finished run of that scene trained under paper-val (python -m "
                             "gst_jax.train --scene S --protocol paper-val --epochs 200 "
                             "--workdir DIR/S); scenes without one take no part in the choice "
                             "(default: the shipped models' own validation windows, in-sample "
                             "for them)")
    args = parser.parse_args(argv)
    out = results_folder(args)
    progress = Progress()
    models = held_out_models(args.rule_models) if args.rule_models else {}
    if args.rule_models and not models:
        parser.error(f"no finished paper-val run under {args.rule_models} (one folder per "
                     f"scene, named {', '.join(SCENES)})")
    in_sample = {s: records_of(f"pretrained:{s}_d", s, out, progress, "val") for s in SCENES}
    held_out = {s: records_of(model, s, out, progress, "val", label=f"paper-val-{s}")
                for s, model in models.items()}
    val = held_out or in_sample
    best, scores = choose(val)
    test = {s: records_of(f"pretrained:{s}_d", s, out, progress) for s in SCENES}
    columns = {"GST": GST_ALONE, "CV": CV_ALONE, "fallback": best}
    if not isinstance(best, Rule):
        # What the rules would have given: the best of them on validation, not chosen there.
        columns["best rule on validation (not chosen)"] = min(
            (r for r in scores if isinstance(r, Rule)), key=scores.get)
    if held_out:
        columns["fallback, fixed in-sample"] = choose(in_sample)[0]
    table = {name: average(test, rule) for name, rule in columns.items()}
    result = {"rule": _described(best),
              "rule_fixed_on": ({"held_out": sorted(held_out), "models": str(args.rule_models)}
                                if held_out else "in_sample"),
              "validation_average_aoe": {"fallback": scores[best], "GST": scores[GST_ALONE],
                                         "CV": scores[CV_ALONE]},
              "validation_rules": [{"rule": rule_text(r), "average_aoe": v}
                                   for r, v in sorted(scores.items(), key=lambda kv: kv[1])],
              "test": {name: {"average": avg, **per_scene}
                       for name, (avg, per_scene) in table.items()},
              "test_rules": {name: _described(rule) for name, rule in columns.items()},
              "test_share_gst": {name: {s: gst_share(r, rule) for s, r in test.items()}
                                 for name, rule in columns.items()},
              "test_difference": {f"{name} - {baseline}": difference(test, rule, key)
                                  for name, rule in columns.items() if name not in ("GST", "CV")
                                  for baseline, key in (("CV", "cv_ade"), ("GST", "model_ade"))
                                  if rule != columns[baseline]},
              "pedestrians": {"val": {s: len(r["cv_ade"]) for s, r in val.items()},
                              "test": {s: len(r["cv_ade"]) for s, r in test.items()}}}
    text = markdown(result, table, held_out, args.rule_models)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fallback.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / "fallback.md").write_text(text)
    print(json.dumps(result, indent=1) if args.json else text)


def markdown(result: dict, table: dict, held_out: dict, models: Path | None) -> str:
    validation = result["validation_average_aoe"]
    where = (f"the validation windows of models trained under paper-val ({models}/<scene>: "
             f"the same 200 epochs on each file's train windows less that last tenth, so "
             f"held out for them) on {', '.join(sorted(held_out))}"
             + ("" if len(held_out) == len(SCENES) else
                f" (no such model of {', '.join(s for s in SCENES if s not in held_out)})")
             if held_out else "each shipped model's own validation split")
    header = ["| " + " | ".join(SCENES) + " | average |", "|---" * (len(SCENES) + 2) + "|"]
    lines = ["# Per person, GST or constant velocity?", "",
             "Paper protocol; each scene's shipped Table I model (GST (D)); 20 samples (hard, tau "
             "0.03); AOE in metres on the fully detected pedestrians. The fallback was chosen "
             "among the candidates below (GST alone, CV alone and rules on what a planner sees "
             "during the observation) by the mean over the scenes of the validation AOE, on "
             f"{where}; the test splits were read only for these tables. Made by `python "
             f"experiments/fallback.py --publish"
             + (f" --rule-models {models}`." if held_out else "`."), "",
             f"Chosen: {result['rule']['text']} (validation average AOE "
             f"{validation['fallback']:.4f}; GST alone {validation['GST']:.4f}, CV alone "
             f"{validation['CV']:.4f})." + _ties(result), "",
             "| test AOE " + header[0], header[1]]
    for name, (avg, per_scene) in table.items():
        lines.append(f"| {name} | " + " | ".join(f"{per_scene[s]:.4f}" for s in SCENES)
                     + f" | {avg:.4f} |")
    lines += ["", "| candidate | rule | " + " | ".join(f"given GST, {s}" for s in SCENES) + " |",
              "|---|---" + "|---" * len(SCENES) + "|"]
    lines += [f"| {name} | {result['test_rules'][name]['text']} | " + " | ".join(
        f"{share[s]:.2f}" for s in SCENES) + " |"
        for name, share in result["test_share_gst"].items() if name not in ("GST", "CV")]
    lines += ["", "Paired per pedestrian, with 95 % intervals (the average's from the scenes' "
              "standard errors):", "", "| test ADE difference " + header[0], header[1]]
    lines += [f"| {name} | " + " | ".join(_interval(parts[s]) for s in (*SCENES, "average"))
              + " |" for name, parts in result["test_difference"].items()]
    fallback, gst, cv = (table[name][0] for name in ("fallback", "GST", "CV"))
    lines += ["", f"The fallback is {'better' if fallback < min(gst, cv) else 'not better'} "
              f"than both on the test average ({fallback:.4f} against GST {gst:.4f} and CV "
              f"{cv:.4f})."]
    if "best rule on validation (not chosen)" in table:
        name = "best rule on validation (not chosen)"
        gain = result["test_difference"][f"{name} - CV"]["average"]
        lines[-1] += (f" It is a predictor alone: no rule beat both on validation. The best "
                      f"rule there gave {table[name][0]:.4f} on test, {_interval(gain)} against "
                      f"CV ({_sign(gain)}): a gain the validation windows did not show.")
    if not held_out:
        lines += ["", "The validation windows (protocol paper-val: the last tenth of each "
                  "file's paper train windows) are windows the shipped models were trained on: "
                  f"in-sample for GST, whose validation average ({validation['GST']:.4f}) beats "
                  f"CV's ({validation['CV']:.4f}) by far more than on test, so that every rule "
                  "chosen there leans to GST. `--rule-models DIR` fixes it on held-out windows "
                  "instead, with models trained under paper-val."]
    lines += ["", "Validation average AOE of every candidate, best first:", "",
              "| candidate | validation average AOE |", "|---|---|"]
    lines += [f"| {r['rule']} | {r['average_aoe']:.4f} |" for r in result["validation_rules"]]
    return "\n".join(lines) + "\n"


def _interval(d: dict) -> str:
    return f"{d['mean']:+.4f} ({d['low']:+.4f} to {d['high']:+.4f})"


def _sign(d: dict) -> str:
    return "spanning zero" if d["low"] <= 0 <= d["high"] else "clear of zero"


def _ties(result: dict) -> str:
    """" 7 candidates tie ...": where the chosen rule's validation AOE is not its own."""
    best = result["validation_average_aoe"]["fallback"]
    tied = sum(r["average_aoe"] == best for r in result["validation_rules"])
    return ("" if tied == 1 else f" {tied} candidates tie at that figure (they choose alike on "
            "every validation person); the tie went to the one giving GST to the fewest "
            "validation people, then to the first listed.")


if __name__ == "__main__":
    main()
