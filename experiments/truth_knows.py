"""What the truth knows that the robot cannot see (issue 90).

The simulator's own rollout of the humans (the study's truth predictor: it knows their goals,
preferred speeds and radii, everyone beyond the sensor's range, and when the shift comes) with
one hidden quantity at a time replaced by what the robot could estimate from its tracks, then
with all of them replaced; each one's distance from the truth (m, mean over the 5 predicted
steps and the humans predicted), beside constant velocity's and the trained models'. The
robot is driven by the sampling MPC against constant velocity over the study's first episodes
(seed 1000); a prediction is counted in the phase its predicted steps lie in: all before the
shift (6 s), spanning it, or all after it.

The estimates:
- goal: 50 m ahead along the last observed velocity (ORCA walks straight to its goal unless
  it avoids someone);
- preferred speed: the last observed speed (over the shift's factor once it has begun);
- radius: 0.4 m, the middle of the humans' 0.3-0.5 m;
- unseen: the humans the robot does not detect now removed;
- clock: the shift's time unknown (the rollout keeps the regime of the present).

    python experiments/truth_knows.py                  # runs/truth_knows/
    python experiments/truth_knows.py --publish        # results/truth_knows.{md,json}
"""

from __future__ import annotations

import argparse
import collections
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from _common import add_results_flags, mpc_states, results_folder
from gst_jax.predictors import GST, ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import (
    CONSTANT_VELOCITY,
    POLICY_SHIFT,
    SPEED_SHIFT,
    CrowdNav,
    EnvParams,
    EnvState,
)

HIDDEN = ("goal", "preferred speed", "radius", "unseen", "clock")
MODELS = ("pretrained:crowdnav_env", "pretrained:crowdnav_env_partial")
# Phases of an episode by the time a prediction is made: its predicted steps all before the
# shift, spanning it, or all after it (the shift at 6 s, 5 steps of 0.25 s).
PHASES = ("before", "spanning", "after")


def estimated(env: CrowdNav, state: EnvState, params: EnvParams, replaced: tuple[str, ...]
              ) -> EnvState:
    """`state` with the hidden quantities `replaced` estimated from the robot's tracks."""
    positions, detected = state.tracks.positions, state.tracks.detected
    velocity = (positions[:, -1] - positions[:, -2]) / params.step_s
    speed = jnp.linalg.norm(velocity, axis=-1)
    shifted = state.time >= params.shift_at_s
    if "goal" in replaced:
        state = state.replace(human_goal=state.human_position + 50.0 * velocity / jnp.maximum(
            speed, 1e-6)[:, None])
    if "preferred speed" in replaced:
        factor = params.speed_factor if env.shift == SPEED_SHIFT else 1.0
        state = state.replace(human_v_pref=jnp.maximum(
            speed / jnp.where(shifted, factor, 1.0), 0.05))
    if "radius" in replaced:
        state = state.replace(human_radius=jnp.full_like(state.human_radius, 0.4))
    if "unseen" in replaced:
        far = 1e4 + 100.0 * jnp.arange(env.num_humans)[:, None]
        state = state.replace(human_position=jnp.where(detected[:, -1:] > 0,
                                                       state.human_position, far))
    if "clock" in replaced:
        state = state.replace(time=jnp.where(shifted, state.time, 0.0))
    return state


def errors_of(shift: str, episodes: int, seed: int) -> dict:
    """{(phase, name): mean distance from the truth (m)} and the predictions counted."""
    env, params = CrowdNav.with_predictor(CONSTANT_VELOCITY, 20, shift=shift)
    rollouts = {"truth's rules, " + name: (name,) for name in HIDDEN}
    rollouts["truth's rules, all estimated"] = HIDDEN
    predictors = {name: jax.jit(lambda state, hidden=hidden: env._truth(
        estimated(env, state, params, hidden), params)) for name, hidden in rollouts.items()}
    cv = ConstantVelocity()
    predictors["constant velocity"] = jax.jit(lambda state: jnp.swapaxes(cv.predict(
        None, None, state.tracks.positions, state.tracks.detected)[0][0], 0, 1))
    for name in MODELS:
        run = load_model(name)
        model = GST(run.model_config)
        predictors[name.split(":")[1]] = jax.jit(lambda state, model=model, weights=run.params:
                                                 jnp.swapaxes(model.predict(
                                                     weights, jax.random.key(0),
                                                     state.tracks.positions,
                                                     state.tracks.detected)[0][0], 0, 1))
    truth = jax.jit(lambda state: env._truth(state, params))
    errors = collections.defaultdict(list)
    for state in mpc_states(env, params, episodes, seed):
        predicted = np.asarray((state.tracks.detected[:, -2:] > 0).all(-1))
        exact = np.asarray(truth(state))                                     # (H, P, 2)
        now = float(state.time)
        phase = PHASES[(now + env.pred_len * params.step_s >= params.shift_at_s)
                       + (now >= params.shift_at_s)]
        for name, predict in predictors.items():
            distance = np.linalg.norm(np.asarray(predict(state)) - exact, axis=-1)
            errors[phase, name].extend(distance.mean(1)[predicted].tolist())
    return {key: (float(np.mean(values)), len(values)) for key, values in errors.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=10, help="episodes (default: 10)")
    parser.add_argument("--seed", type=int, default=1000, help="the study's episodes: 1000")
    add_results_flags(parser, "truth_knows", "truth_knows.md and .json", runs=False)
    args = parser.parse_args()
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for shift in (SPEED_SHIFT, POLICY_SHIFT):
        started = time.perf_counter()
        errors = errors_of(shift, args.episodes, args.seed)
        for (phase, name), (error, count) in errors.items():
            rows.append({"shift": shift, "phase": phase, "predictor": name,
                         "distance_m": round(error, 4), "predictions": count})
        print(f"{shift}: {time.perf_counter() - started:.0f} s", flush=True)
    names = list(dict.fromkeys(r["predictor"] for r in rows))
    described, estimates = __doc__.split("\n\n")[1:3]
    lines = ["# What the truth knows that the robot cannot see", "",
             described.replace("\n", " ") + f" {args.episodes} episodes; made by `python "
             "experiments/truth_knows.py --publish`; the last row counts the predictions.", "",
             estimates, "",
             "| predictor | " + " | ".join(f"{s} shift, {p}" for s in (SPEED_SHIFT, POLICY_SHIFT)
                                            for p in PHASES) + " |",
             "|---" * (1 + 2 * len(PHASES)) + "|"]
    cell = {(r["shift"], r["phase"], r["predictor"]): r for r in rows}
    for name in names:
        lines.append(f"| {name} | " + " | ".join(
            f"{cell[s, p, name]['distance_m']:.3f}" for s in (SPEED_SHIFT, POLICY_SHIFT)
            for p in PHASES) + " |")
    lines.append("| predictions | " + " | ".join(
        str(cell[s, p, names[0]]["predictions"]) for s in (SPEED_SHIFT, POLICY_SHIFT)
        for p in PHASES) + " |")
    text = "\n".join(lines) + "\n"
    (out / "truth_knows.md").write_text(text)
    (out / "truth_knows.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
