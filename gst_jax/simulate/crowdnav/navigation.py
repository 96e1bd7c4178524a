"""Planners evaluated in CrowdNav++'s task: many episodes through one jitted, vmapped program,
a chunk of them at a time, and what CrowdNav++ and ICP report of them.

Each episode runs `environment.CrowdNav.step_env` under a planner until it ends (arrival,
collision, or the timeout after 49 s: at most 197 steps) and then stands still. Measures,
as CrowdNav++'s test script reports them (`rl/evaluation.py`): success, collision and
timeout rates; navigation time over the successful episodes, path length over all; the
intrusion ratio, the fraction of an episode's steps in which a human's actual position over
the next 5 steps comes within 0.6 m (robot + human radius) of the robot (CrowdNav++ rolls
ORCA forward for this, without goal changes or replaced humans; here the humans' recorded
positions are those futures, the ones they took, also where they react to the robot).
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

from gst_jax import resources
from gst_jax.adaptation import METHODS
from gst_jax.conformal import Regions
from gst_jax.errors import RunError
from gst_jax.predict import check_compiler_room, check_memory, estimate
from gst_jax.progress import Progress
from gst_jax.simulate.crowdnav.environment import (
    COLLISION,
    CONSTANT_VELOCITY,
    NO_SHIFT,
    POLICY_SHIFT,
    REACH_GOAL,
    STANDING,
    TIMEOUT,
    TRUTH,
    CrowdNav,
    EnvParams,
    Observation,
)
from gst_jax.simulate.crowdnav.figures import animate_navigation
from gst_jax.simulate.crowdnav.planner import DecisionCalibration, PlannerState, SamplingMPC
from gst_jax.simulate.crowdnav.records import DECISION, record_name

# A planner: (key, its state, observation) -> (velocity (2,), its next state).
Planner = Callable[[jax.Array, PlannerState, Observation], tuple[jax.Array, PlannerState]]


# The sampling MPC's variants by what it plans against: (`CrowdNav`'s model, None for GST's,
# loaded from --model; the name of that predictor in records).
PLANNERS = {"mpc": (None, "gst"), "cv-mpc": (CONSTANT_VELOCITY, "cv"),
            "standing-mpc": (STANDING, "none"), "truth-mpc": (TRUTH, "truth")}


def described_run(planner: str, regions: str, alpha: float = 0.1, humans: str = "orca",
                  reactive: bool = False, num_humans: int = 20, shift: str = NO_SHIFT,
                  model: str | None = None, adaptation: str = "none",
                  fresh_tracks: bool = False) -> dict:
    """What names an evaluation and its record (`evaluate`'s `described`): the planner, its
    predictor as records name it (gst, cv, none: people standing, truth), the discs
    (`records.REGIONS`: a conformal method, "none", or "decision": no discs, a margin
    calibrated online), the humans (`humans` "orca" or "social-force"), GST's model for
    planner mpc, the online correction of the predictions (`gst_jax.adaptation.METHODS`, or
    "none"), and whether a replaced human's history starts empty (`CrowdNav.fresh_tracks`)."""
    if shift == POLICY_SHIFT and humans != "orca":
        raise RunError("--shift policy switches ORCA humans to social force: it needs "
                       "--humans orca")
    return {"planner": planner, "predictor": PLANNERS[planner][1], "regions": regions,
            "alpha": alpha, "humans": humans, "reactive": reactive, "num_humans": num_humans,
            "shift": shift, "model": model if planner == "mpc" else None,
            "adaptation": adaptation, **({"fresh_tracks": True} if fresh_tracks else {})}


def environment_for(described: dict, gst=None) -> tuple[CrowdNav, EnvParams]:
    """The environment a described evaluation plays; `gst`: the loaded model for planner
    mpc."""
    regions = (None if described["regions"] in ("none", DECISION) else
               Regions(described["regions"], described["alpha"]))
    adaptation = described.get("adaptation", "none")
    return CrowdNav.with_predictor(PLANNERS[described["planner"]][0] or gst,
                                   described["num_humans"], regions,
                                   described["humans"].replace("-", "_"),
                                   described["reactive"], described["shift"],
                                   None if adaptation == "none" else METHODS[adaptation](),
                                   described.get("fresh_tracks", False))


def max_steps(params: EnvParams) -> int:
    """Steps until the timeout fires: at the step that begins at time_limit - 1 seconds."""
    return round((params.time_limit_s - 1) / params.step_s) + 1


# Episodes per compiled program: memory is bounded by one chunk's, whatever the count. XLA's
# memory analysis (CPU) of crowdnav_sj_rand's program with 256 plans: 0.235 MB of temporaries
# and 0.033 MB of outputs per episode, linear from 10 to 1000 (268 MB): a million episodes
# in one program would ask for 268 GB.
CHUNK = 1000


def _episode(env: CrowdNav, params: EnvParams, planner: Planner, init: PlannerState
             ) -> Callable[[jax.Array], dict]:
    """One episode of `planner` from its key: its arrays (`run_episodes`)."""
    steps = max_steps(params)

    def episode(key):
        reset_key, run_key = jax.random.split(key)
        obs, state = env.reset(reset_key, params)

        def step(carry, key):
            obs, state, planner_state, finished, outcome, ended_at, closest, t = carry
            plan_key, env_key = jax.random.split(key)
            action, planner_state = planner(plan_key, planner_state, obs)
            new_obs, new_state, _, done, info = env.step_env(env_key, state, action, params)
            keep = lambda new, old: jnp.where(finished, old, new)
            obs = jax.tree.map(keep, new_obs, obs)
            state = jax.tree.map(keep, new_state, state)
            ends = done & ~finished
            outcome = jnp.where(ends, info["outcome"], outcome)
            ended_at = jnp.where(ends, t + 1, ended_at)
            closest = jnp.where(finished, closest, jnp.minimum(closest, info["min_distance"]))
            carry = (obs, state, planner_state, finished | done, outcome, ended_at, closest,
                     t + 1)
            return carry, (state.robot_position, state.human_position, obs.radii.mean())

        carry = (obs, state, init, jnp.asarray(False), jnp.asarray(TIMEOUT),
                 jnp.asarray(steps), jnp.asarray(jnp.inf), jnp.asarray(0))
        carry, (robot, humans, radii) = jax.lax.scan(step, carry, jax.random.split(run_key,
                                                                                    steps))
        robot = jnp.concatenate([state.robot_position[None], robot])
        humans = jnp.concatenate([state.human_position[None], humans])
        return {"robot": robot, "humans": humans, "goal": state.robot_goal,
                "outcome": carry[4], "steps": carry[5], "closest_m": carry[6],
                "radii_mean": radii.mean()}

    return episode


def run_episodes(env: CrowdNav, params: EnvParams, planner: Planner, init: PlannerState,
                 count: int, seed: int = 0, *, chunk: int = CHUNK, keep: int = 0,
                 progress: Progress | None = None) -> tuple[dict, float, float]:
    """`count` episodes of `planner`, `chunk` at a time through one compiled program (the
    last chunk padded), so that memory does not grow with `count`: (arrays, compile
    seconds, run seconds). Arrays: `episode_measures` of every episode (E,), and of the
    first `keep` episodes the robot's (K, S+1, 2) and humans' (K, S+1, H, 2) positions
    (still after the end) and the goal (K, 2). Episode i plays from the i-th key of
    split(key(seed), count) in a lane of its own, whatever `chunk`; on a CPU the number of
    lanes can change the rounding of the positions (docs/navigation.md). A chunk whose memory
    (XLA's estimate) this process cannot hold is refused in one line (`DataError`) with the
    chunk that fits. `progress` counts the episodes done, with an ETA."""
    keys = jax.random.split(jax.random.key(seed), count)
    size = min(count, chunk)
    started = time.perf_counter()
    what = f"{size} navigation episodes at once"
    check_compiler_room(what)
    traced = jax.jit(jax.vmap(_episode(env, params, planner, init))).trace(keys[:size])
    compiled = traced.lower().compile()
    cost = estimate(compiled, traced.jaxpr, jax.devices()[:1])
    available = resources.available_memory(jax.devices()[0])
    if available and cost.bytes_needed:
        # The memory grows with the chunk: the fix names the chunk that fits.
        fits = max(1, size * available[0] // cost.bytes_needed)
        check_memory(cost, jax.devices()[0], what, f"use --chunk {fits} or less")
    compile_s = time.perf_counter() - started
    started = time.perf_counter()
    parts = []
    for first in range(0, count, size):
        taken = min(size, count - first)
        lanes = np.minimum(np.arange(first, first + size), count - 1)    # the last padded
        out = jax.tree.map(lambda a: np.asarray(a)[:taken], compiled(keys[lanes]))
        part = episode_measures(out, params)
        kept = min(max(keep - first, 0), taken)
        parts.append({**part, **{k: out[k][:kept] for k in ("robot", "humans", "goal")}})
        if progress:
            progress.count("episodes", first + taken, count, started)
    arrays = {k: np.concatenate([part[k] for part in parts]) for k in parts[0]}
    return arrays, compile_s, time.perf_counter() - started


def episode_measures(episodes: dict, params: EnvParams, intrusion_steps: int = 5,
                     intrusion_distance: float = 0.6) -> dict:
    """Per episode (E,), from its positions (robot (E, S+1, 2), humans (E, S+1, H, 2)),
    outcome, steps (the step it ended at), closest_m (the least distance between the robot's
    surface and a human's before each step of the episode, CrowdNav++'s `min_distance`:
    negative in a collision) and radii_mean (the mean conformal radius the robot was given):
    those and path_length_m and intrusion_ratio (module docstring)."""
    steps = episodes["steps"]
    robot, humans = episodes["robot"], episodes["humans"]
    moved = np.linalg.norm(np.diff(robot, axis=1), axis=-1)                  # (E, S)
    live = np.arange(moved.shape[1])[None] < steps[:, None]
    # Step t intrudes when a human's position at t+1..t+5 comes near the robot's at t.
    total = robot.shape[1]
    near = np.zeros(robot.shape[:2], bool)
    for k in range(1, intrusion_steps + 1):
        ahead = np.linalg.norm(humans[:, k:] - robot[:, :total - k, None], axis=-1)
        near[:, :total - k] |= (ahead < intrusion_distance).any(axis=-1)
    counted = np.arange(total)[None] < steps[:, None]
    return {"outcome": episodes["outcome"], "steps": steps, "closest_m": episodes["closest_m"],
            "radii_mean": episodes["radii_mean"], "path_length_m": (moved * live).sum(axis=1),
            "intrusion_ratio": (near & counted).sum(axis=1) / np.maximum(steps, 1)}


def navigation_measures(measures: dict, params: EnvParams) -> dict:
    """CrowdNav++'s test measures (module docstring) of `episode_measures`' arrays."""
    outcome, steps = measures["outcome"], measures["steps"]
    success = outcome == REACH_GOAL
    rate = lambda mask: float(mask.mean())
    over_success = lambda values: float(values[success].mean()) if success.any() else math.nan
    return {"episodes": int(len(outcome)), "success": rate(success),
            "collision": rate(outcome == COLLISION), "timeout": rate(outcome == TIMEOUT),
            "navigation_time_s": over_success(steps * params.step_s),
            "path_length_m": float(measures["path_length_m"].mean()),
            "intrusion_ratio": float(measures["intrusion_ratio"].mean()),
            "mean_radius_m": float(np.nanmean(measures["radii_mean"]))}


def per_episode(measures: dict, params: EnvParams) -> dict:
    """Each episode's outcome ("success", "collision" or "timeout"), time_s (when it ended),
    closest_m and intrusion_ratio (`episode_measures`) as lists in episode (seed) order, so
    that two evaluations of the same episodes compare episode by episode
    (`gst_jax.simulate.crowdnav.paired`)."""
    names = {REACH_GOAL: "success", COLLISION: "collision", TIMEOUT: "timeout"}
    return {"outcome": [names[int(o)] for o in measures["outcome"]],
            "time_s": [round(float(s) * params.step_s, 2) for s in measures["steps"]],
            "closest_m": [round(float(d), 4) for d in measures["closest_m"]],
            "intrusion_ratio": [round(float(r), 4) for r in measures["intrusion_ratio"]]}


def evaluate_described(described: dict, gst, plans: int, count: int, seed: int, out: Path,
                       gifs: int = 0, **options) -> dict:
    """`evaluate` of the sampling MPC with `plans` plans in the environment `described`
    (`described_run`; `gst`: the loaded model for planner mpc)."""
    env, params = environment_for(described, gst)
    calibration = DecisionCalibration() if described["regions"] == DECISION else None
    planner = SamplingMPC(num_plans=plans, horizon=env.pred_len, step_s=params.step_s,
                          calibration=calibration)
    return evaluate(env, params, planner, count, seed, out, described, gifs, **options)


def evaluate(env: CrowdNav, params: EnvParams, planner: SamplingMPC, count: int, seed: int,
             out: Path, described: dict, gifs: int = 0, *, overwrite: bool = False,
             chunk: int = CHUNK, progress: Progress | None = None) -> dict:
    """`count` episodes of `planner` measured: `described` (its "planner" and "regions",
    and "humans", "reactive", "num_humans", "shift" where they are not the defaults, name
    the files), the measures and the timings,
    written to out/`record_name`.json, and a GIF of each of the first `gifs` episodes beside
    it. An existing record is replaced only with `overwrite` (refused before compiling)."""
    name = record_name(described["planner"], described["regions"],
                       described.get("humans", "orca"), count, seed,
                       described.get("reactive", False), described.get("num_humans", 20),
                       described.get("shift", NO_SHIFT), described.get("model"),
                       described.get("adaptation", "none"), described.get("fresh_tracks", False))
    if (out / f"{name}.json").exists() and not overwrite:
        raise RunError(f"{out / name}.json exists: a run of the same {count} episodes; "
                       f"--overwrite replaces it, another --workdir keeps it")
    episodes, compile_s, run_s = run_episodes(env, params, planner, planner.init(), count,
                                              seed=seed, chunk=chunk, keep=gifs,
                                              progress=progress)
    result = {**described, "seed": seed, **navigation_measures(episodes, params),
              "compile_s": round(compile_s, 1), "run_s": round(run_s, 1),
              "per_episode": per_episode(episodes, params)}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(result, indent=1) + "\n")
    for e in range(min(gifs, count)):
        animate_navigation(episodes["robot"][e], episodes["humans"][e], episodes["goal"][e],
                           int(episodes["steps"][e]), out / f"{name}-episode{e}.gif",
                           f"{name}, episode {e}")
    if progress:
        progress.line(f"written: {out / name}.json" + (f" and {min(gifs, count)} GIFs beside it"
                                                      if gifs else ""))
    return result
