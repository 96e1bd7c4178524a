"""CrowdNav++'s task with GST in the loop as one jitted program: environment steps per
second, and one MPC planning step (`gst_jax.simulate.crowdnav.environment`, `planner`).

    python benchmarks/bench_env.py                               # 64, 256, 1024 environments
    python benchmarks/bench_env.py --envs 64 --predictor gst cv none --steps 100

Throughput: `--envs` environments vmapped, `--steps` steps of `CrowdNav.step` (auto-reset
included) in one `lax.scan` under a fixed action (the velocity towards the goal), predictions
by CrowdNav++'s randomized-human predictor (`pretrained:crowdnav_sj_rand`, mean mode, 20
humans, 5 observed and 5 predicted steps), DtACI regions; the best of `--repeats` timed calls
after a compiling one; the humans walk by ORCA or (`--humans social_force`) social force.
Beside it, two parts of a step timed alone on the states of 40 steps in (best of 5 calls):
the humans' new velocities and the predictor's forward pass. Planning: the `SamplingMPC` of
256 plans on one observation of 20 humans, jitted, median of `--calls`.
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax

from common import print_table, record
from gst_jax.conformal import Regions
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import (
    CONSTANT_VELOCITY,
    ORCA,
    SOCIAL_FORCE,
    CrowdNav,
    EnvParams,
)
from gst_jax.simulate.crowdnav.planner import SamplingMPC
from gst_jax.stream import StreamModel, predict_slots

MODEL = "pretrained:crowdnav_sj_rand"


def environment(predictor: str, humans: str = ORCA) -> tuple[CrowdNav, EnvParams]:
    model = {"gst": lambda: load_model(MODEL), "cv": lambda: CONSTANT_VELOCITY,
             "none": lambda: None}[predictor]()
    return CrowdNav.with_predictor(model, regions=Regions("dtaci", 0.1) if model else None,
                                   human_policy=humans)


def time_steps(env: CrowdNav, params: EnvParams, envs: int, steps: int, repeats: int) -> dict:
    def rollout(keys):
        _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def step(states, key):
            action = states.robot_goal - states.robot_position
            _, states, reward, _, _ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(key, envs), states, action, params)
            return states, reward.mean()

        return jax.lax.scan(step, states, jax.random.split(keys[0], steps))[1]

    run = jax.jit(rollout)
    keys = jax.random.split(jax.random.key(0), envs)
    started = time.perf_counter()
    jax.block_until_ready(run(keys))
    compile_s = time.perf_counter() - started
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        jax.block_until_ready(run(keys))
        seconds.append(time.perf_counter() - started)
    return {"steps_per_s": envs * steps / min(seconds), "best_s": min(seconds),
            "compile_s": compile_s}


def time_parts(env: CrowdNav, params: EnvParams, envs: int) -> dict:
    """Milliseconds of the humans' new velocities and of the predictor's forward pass alone,
    best of 5 calls, on the states 40 steps into `envs` episodes."""
    keys = jax.random.split(jax.random.key(0), envs)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(keys, params)
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    for t in range(40):
        _, states, *_ = step(jax.random.split(jax.random.key(t), envs), states,
                             states.robot_goal - states.robot_position, params)
    parts = {"humans_ms": jax.vmap(lambda state: env.human_velocities(state, params))}
    if isinstance(env.model, StreamModel):
        parts["predictor_ms"] = jax.vmap(
            lambda key, state: predict_slots(env.model, params.predictor, key, state.tracks))
    timed = {}
    for name, part in parts.items():
        part = jax.jit(part)
        inputs = (states,) if name == "humans_ms" else (keys, states)
        jax.block_until_ready(part(*inputs))
        seconds = []
        for _ in range(5):
            started = time.perf_counter()
            jax.block_until_ready(part(*inputs))
            seconds.append(time.perf_counter() - started)
        timed[name] = 1e3 * min(seconds)
    return timed


def time_planner(calls: int) -> dict:
    env, params = environment("gst")
    obs, _ = jax.jit(env.reset)(jax.random.key(0), params)
    planner = SamplingMPC()
    plan = jax.jit(planner.__call__)
    state = planner.init()
    seconds = []
    for call in range(calls + 1):
        started = time.perf_counter()
        action, state = plan(jax.random.key(call), state, obs)
        action.block_until_ready()
        seconds.append(time.perf_counter() - started)
    return {"median_ms": 1e3 * statistics.median(seconds[1:]), "compile_s": seconds[0],
            "plans": planner.num_plans, "humans": env.num_humans}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="*", type=int, default=[64, 256, 1024])
    parser.add_argument("--predictor", nargs="*", default=["gst"], choices=("gst", "cv", "none"))
    parser.add_argument("--humans", nargs="*", default=[ORCA], choices=(ORCA, SOCIAL_FORCE),
                        help="how the humans walk (default: orca)")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--note", default="", help="recorded with the rows (e.g. the load)")
    args = parser.parse_args()
    rows = []
    for humans in args.humans:
        for predictor in args.predictor:
            env, params = environment(predictor, humans)
            for envs in args.envs:
                result = time_steps(env, params, envs, args.steps, args.repeats)
                result |= time_parts(env, params, envs)
                rows.append(record("env", humans=humans, predictor=predictor, envs=envs,
                                   steps=args.steps, note=args.note, **result))
    print_table(rows, ["humans", "predictor", "envs", "steps_per_s", "best_s", "compile_s",
                       "humans_ms", "predictor_ms"])
    planning = record("mpc", calls=args.calls, note=args.note, **time_planner(args.calls))
    print_table([planning], ["plans", "humans", "median_ms", "compile_s"])


if __name__ == "__main__":
    main()
