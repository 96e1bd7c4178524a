"""Planners evaluated in CrowdNav++'s task: many episodes as one jitted, vmapped program, and
what CrowdNav++ and ICP report of them.

Each episode runs `environment.CrowdNav.step_env` under a planner until it ends (arrival,
collision, or the timeout after 49 s: at most 197 steps) and then stands still. Measures,
as CrowdNav++'s test script reports them (`rl/evaluation.py`): success, collision and
timeout rates; navigation time over the successful episodes, path length over all; the
intrusion ratio, the fraction of an episode's steps in which a human's actual position over
the next 5 steps comes within 0.6 m (robot + human radius) of the robot (CrowdNav++ rolls
ORCA forward for this; here the humans' recorded positions are those futures, which they
are, as they ignore the robot, save for goal changes and replaced humans).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.simulate.environment import (COLLISION, REACH_GOAL, TIMEOUT, CrowdNav, EnvParams,
                                          Observation)
from gst_jax.simulate.figures import animate_navigation
from gst_jax.simulate.planner import PlannerState, SamplingMPC

# A planner: (key, its state, observation) -> (velocity (2,), its next state).
Planner = Callable[[jax.Array, PlannerState, Observation], tuple[jax.Array, PlannerState]]


def max_steps(params: EnvParams) -> int:
    """Steps until the timeout fires: at the step that begins at time_limit - 1 seconds."""
    return round((params.time_limit_s - 1) / params.step_s) + 1


def run_episodes(env: CrowdNav, params: EnvParams, planner: Planner, init: PlannerState,
                 count: int, seed: int = 0) -> tuple[dict, float, float]:
    """`count` episodes of `planner`: (arrays per episode, compile seconds, run seconds).
    Arrays: robot (E, S+1, 2) and humans (E, S+1, H, 2) positions (still after the end),
    goal (E, 2), outcome (E,), steps (E,) the step it ended at, radii_mean (E,) the mean
    conformal radius the robot was given."""
    steps = max_steps(params)

    def episode(key):
        reset_key, run_key = jax.random.split(key)
        obs, state = env.reset(reset_key, params)

        def step(carry, key):
            obs, state, planner_state, finished, outcome, ended_at, t = carry
            plan_key, env_key = jax.random.split(key)
            action, planner_state = planner(plan_key, planner_state, obs)
            new_obs, new_state, _, done, info = env.step_env(env_key, state, action, params)
            keep = lambda new, old: jnp.where(finished, old, new)
            obs = jax.tree.map(keep, new_obs, obs)
            state = jax.tree.map(keep, new_state, state)
            ends = done & ~finished
            outcome = jnp.where(ends, info["outcome"], outcome)
            ended_at = jnp.where(ends, t + 1, ended_at)
            carry = (obs, state, planner_state, finished | done, outcome, ended_at, t + 1)
            return carry, (state.robot_position, state.human_position, obs.radii.mean())

        carry = (obs, state, init, jnp.asarray(False), jnp.asarray(TIMEOUT),
                 jnp.asarray(steps), jnp.asarray(0))
        carry, (robot, humans, radii) = jax.lax.scan(step, carry, jax.random.split(run_key,
                                                                                    steps))
        robot = jnp.concatenate([state.robot_position[None], robot])
        humans = jnp.concatenate([state.human_position[None], humans])
        return {"robot": robot, "humans": humans, "goal": state.robot_goal,
                "outcome": carry[4], "steps": carry[5], "radii_mean": radii.mean()}

    run = jax.jit(jax.vmap(episode))
    keys = jax.random.split(jax.random.key(seed), count)
    started = time.perf_counter()
    compiled = run.lower(keys).compile()
    compile_s = time.perf_counter() - started
    started = time.perf_counter()
    out = jax.block_until_ready(compiled(keys))
    return jax.tree.map(np.asarray, out), compile_s, time.perf_counter() - started


def navigation_measures(episodes: dict, params: EnvParams, intrusion_steps: int = 5,
                        intrusion_distance: float = 0.6) -> dict:
    """CrowdNav++'s test measures of `run_episodes`' arrays (module docstring)."""
    outcome, steps = episodes["outcome"], episodes["steps"]
    success = outcome == REACH_GOAL
    robot, humans = episodes["robot"], episodes["humans"]
    moved = np.linalg.norm(np.diff(robot, axis=1), axis=-1)                  # (E, S)
    live = np.arange(moved.shape[1])[None] < steps[:, None]
    path = (moved * live).sum(axis=1)
    # Step t intrudes when a human's position at t+1..t+5 comes near the robot's at t.
    total = robot.shape[1]
    near = np.zeros(robot.shape[:2], bool)
    for k in range(1, intrusion_steps + 1):
        ahead = np.linalg.norm(humans[:, k:] - robot[:, :total - k, None], axis=-1)
        near[:, :total - k] |= (ahead < intrusion_distance).any(axis=-1)
    counted = np.arange(total)[None] < steps[:, None]
    intrusion = (near & counted).sum(axis=1) / np.maximum(steps, 1)
    rate = lambda mask: float(mask.mean())
    over_success = lambda values: float(values[success].mean()) if success.any() else math.nan
    return {"episodes": int(len(outcome)), "success": rate(success),
            "collision": rate(outcome == COLLISION), "timeout": rate(outcome == TIMEOUT),
            "navigation_time_s": over_success(steps * params.step_s),
            "path_length_m": float(path.mean()),
            "intrusion_ratio": float(intrusion.mean()),
            "mean_radius_m": float(np.nanmean(episodes["radii_mean"]))}



def record_name(planner: str, regions: str, humans: str, seed: int) -> str:
    """The stem of an evaluation's files: PLANNER-REGIONS[-HUMANS]-seedSEED (ORCA's
    humans, the default, unnamed)."""
    return "-".join([planner, regions, *([humans] if humans != "orca" else []), f"seed{seed}"])


def evaluate(env: CrowdNav, params: EnvParams, planner: SamplingMPC, count: int, seed: int,
             out: Path, described: dict, gifs: int = 0) -> dict:
    """`count` episodes of `planner` measured: `described` (its "planner" and "regions",
    and "humans" where they are not ORCA's, name the files), the measures and the timings,
    written to out/PLANNER-REGIONS[-HUMANS]-seedSEED.json, and a GIF of each of the first
    `gifs` episodes beside it."""
    name = record_name(described["planner"], described["regions"],
                       described.get("humans", "orca"), seed)
    episodes, compile_s, run_s = run_episodes(env, params, planner, planner.init(), count,
                                              seed=seed)
    result = {**described, "seed": seed, **navigation_measures(episodes, params),
              "compile_s": round(compile_s, 1), "run_s": round(run_s, 1)}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    for e in range(min(gifs, count)):
        animate_navigation(episodes["robot"][e], episodes["humans"][e], episodes["goal"][e],
                           int(episodes["steps"][e]), out / f"{name}-episode{e}.gif",
                           f"{name}, episode {e}")
    return result
