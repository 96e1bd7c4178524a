"""How accurate must a prediction be before the planner gains from it? (issue 90): the sampling
MPC against the simulator's own futures moved a share w of the way toward constant velocity's,

    future = truth + w (constant velocity - truth),     w = 0 (truth) ... 1 (CV),

over the navigation study's episodes (seed 1000 on, no discs), in the speed and the policy
shift. Along w the planner's error grows from none to CV's in the direction CV errs, so the
success at each w says what share of the truth's margin a predictor of that accuracy could
keep, and the ADE column (against the truth, over the humans predicted, the episodes' every
step) says how accurate that is. Each success is paired with the truth's and CV's rows of the
study (results/runs/navigation), which play the same episodes.

    python experiments/accuracy_needed.py                 # runs/accuracy_needed/
    python experiments/accuracy_needed.py --publish       # results/accuracy_needed.{md,json}

A cell whose record is in the output folder is not run again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from _common import RESULTS, add_results_flags, mpc_states, results_folder
from gst_jax.paired import paired_rates
from gst_jax.predictors import ConstantVelocity, TruthFn, last_two_detected
from gst_jax.simulate.crowdnav.environment import CrowdNav, EnvParams
from gst_jax.simulate.crowdnav.navigation import navigation_measures, per_episode, run_episodes
from gst_jax.simulate.crowdnav.planner import SamplingMPC

SHIFTS = ("speed", "policy")
WEIGHTS = (0.25, 0.5, 0.75)
STUDY = RESULTS / "runs" / "navigation"


@dataclasses.dataclass(frozen=True)
class TruthTowardCV(ConstantVelocity):
    """The simulator's futures moved `weight` of the way toward constant velocity's."""

    weight: float = 0.5

    def predict(self, params, key, positions, detected, truth: TruthFn | None = None):
        assert truth is not None, "only a simulator gives the truth"
        cv, predicted = super().predict(params, key, positions, detected)
        exact = jnp.swapaxes(truth(), 0, 1)[None]                           # (1, P, H, 2)
        return exact + self.weight * (cv - exact), last_two_detected(detected)


def ade_against_truth(env: CrowdNav, params: EnvParams, weight: float, episodes: int,
                      seed: int) -> float:
    """The blend's mean displacement from the truth (m) over the humans predicted at every
    step of the first `episodes` episodes, the robot driven by the MPC against the blend
    (the cell's planner, its own draws; error grows linearly in w, so a few suffice)."""
    truth = jax.jit(lambda state: env._truth(state, params))
    cv = ConstantVelocity(pred_len=env.pred_len)
    errors = []
    for state in mpc_states(env, params, episodes, seed):
        futures, predicted = cv.predict(None, None, state.tracks.positions, state.tracks.detected)
        exact = np.asarray(truth(state))                                     # (H, P, 2)
        offset = np.linalg.norm(np.swapaxes(np.asarray(futures[0]), 0, 1) - exact, axis=-1)
        errors.extend((weight * offset.mean(1))[np.asarray(predicted)].tolist())
    return float(np.mean(errors))


def study_row(shift: str, predictor: str) -> dict:
    """The study's record of `predictor` (truth-mpc or cv-mpc) with no discs in `shift`."""
    return json.loads((STUDY / f"{predictor}-mpc-none-shift{shift}-episodes500-seed1000.json"
                       ).read_text())


def run_cell(shift: str, weight: float, episodes: int, seed: int, out: Path) -> dict:
    path = out / f"truth-toward-cv-{weight:g}-shift{shift}-episodes{episodes}-seed{seed}.json"
    if path.exists():
        return json.loads(path.read_text())
    env, params = CrowdNav.with_predictor(TruthTowardCV(weight=weight), shift=shift)
    planner = SamplingMPC(horizon=env.pred_len, step_s=params.step_s)
    measures, compile_s, run_s = run_episodes(env, params, planner, planner.init(), episodes,
                                              seed=seed)
    record = {"shift": shift, "weight": weight, "seed": seed,
              **navigation_measures(measures, params),
              "ade_m": round(ade_against_truth(env, params, weight, 5, seed), 4),
              "compile_s": round(compile_s, 1), "run_s": round(run_s, 1),
              "per_episode": per_episode(measures, params)}
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    return record


def table(cells: list[dict]) -> list[str]:
    lines = ["| shift | w | ADE against the truth (m) | success | minus CV (95 % paired interval) "
             "| share of the truth's margin (both without discs) |", "|---" * 6 + "|"]
    for shift in SHIFTS:
        truth, cv = study_row(shift, "truth"), study_row(shift, "cv")
        margin = truth["success"] - cv["success"]
        outcome = lambda record: np.array(record["per_episode"]["outcome"]) == "success"
        rows = [(0.0, 0.0, truth), *[(c["weight"], c["ade_m"], c) for c in cells
                                     if c["shift"] == shift], (1.0, None, cv)]
        for weight, ade, row in rows:
            paired = paired_rates(outcome(row), outcome(cv))
            ade_text = "CV's" if ade is None else f"{ade:.3f}"
            lines.append(f"| {shift} | {weight:g} | {ade_text} | {row['success']:.3f} | "
                         f"{paired['difference']:+.3f} ({paired['low']:+.3f} to "
                         f"{paired['high']:+.3f}) | {paired['difference'] / margin:+.2f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=500, help="episodes (default: 500)")
    parser.add_argument("--seed", type=int, default=1000, help="the study's episodes: 1000")
    add_results_flags(parser, "accuracy_needed", "the records and accuracy_needed.md",
                      runs=False)
    args = parser.parse_args()
    out = results_folder(args)
    runs = out / "runs" / "accuracy_needed" if args.publish else out
    cells = []
    for shift in SHIFTS:
        for weight in WEIGHTS:
            started = time.perf_counter()
            cells.append(run_cell(shift, weight, args.episodes, args.seed, runs))
            print(f"{shift} w {weight:g}: success {cells[-1]['success']:.3f}, ADE "
                  f"{cells[-1]['ade_m']:.3f} m ({time.perf_counter() - started:.0f} s)",
                  flush=True)
    text = "\n".join([
        "# How accurate a prediction the planner needs", "",
        "The sampling MPC against the simulator's own futures moved a share w of the way toward "
        "constant velocity's (future = truth + w (CV - truth)), no discs, over the navigation "
        f"study's {args.episodes} episodes (seed {args.seed}); w = 0 and 1 are the study's truth "
        "and CV rows. ADE: the blend's mean distance from the truth over the humans predicted "
        "at every step of the first 5 episodes, before and after the shift together. Each "
        "success is paired with CV's over the same episodes. Made by `python "
        "experiments/accuracy_needed.py --publish`.", "", *table(cells), ""])
    (out / "accuracy_needed.md").write_text(text)
    (out / "accuracy_needed.json").write_text(json.dumps(
        [{k: v for k, v in c.items() if k != "per_episode"} for c in cells], indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
