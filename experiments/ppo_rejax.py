"""Train a robot's policy with PPO from rejax (a maintained JAX RL library) in CrowdNav++'s
task with GST in the loop: gst_jax.simulate.crowdnav.environment.CrowdNav as it is, behind the thin
adapter below (a flat observation, gymnax's spaces, rejax's max_steps_in_episode).

    pip install ".[rl]"            # rejax and gymnax: the rl extra
    python experiments/ppo_rejax.py --timesteps 2000000 --envs 64
    python experiments/ppo_rejax.py --timesteps 20000000 --chunk 500000 --episodes 100 \
        --workdir runs/ppo                       # a learning curve, resumable

The whole training (environments, GST with DtACI discs, PPO's updates) is one jitted program.
This is the example, not CrowdNav++'s RL training (its recurrent attention policy over 20 M
steps): it reports the seconds it took and, with --episodes, CrowdNav++'s measures of the
trained policy (`gst_jax.simulate.crowdnav.navigation`). With --chunk, the program trains --chunk
steps at a time and after each measures the policy over --episodes test episodes, appending
a point of the learning curve to <workdir>/curve.jsonl and saving the training state beside
it (state.msgpack), from which a rerun continues; it says when success first reached 0.9.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import serialization, struct

from gst_jax.conformal import Regions
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import (
    CONSTANT_VELOCITY,
    CrowdNav,
    EnvParams,
    Observation,
)
from gst_jax.simulate.crowdnav.navigation import max_steps, navigation_measures, run_episodes

if TYPE_CHECKING:                   # rejax and gymnax: the rl extra, imported where used
    from rejax import PPO


@struct.dataclass
class AdapterParams:
    env: EnvParams
    max_steps_in_episode: int = struct.field(pytree_node=False, default=197)


def flat(obs: Observation) -> jax.Array:
    """The observation as one vector: the goal relative to the robot, the robot's velocity,
    every human's row of relative positions (nearest first) and the radii around them."""
    to_goal = obs.robot_node[3:5] - obs.robot_node[:2]
    return jnp.concatenate([to_goal, obs.temporal_edges, obs.spatial_edges.ravel(),
                            obs.radii.ravel()])


@struct.dataclass
class FlatCrowdNav:
    """CrowdNav behind gymnax's interface, as rejax reads it."""

    env: CrowdNav = struct.field(pytree_node=False)

    @property
    def default_params(self) -> AdapterParams:
        return AdapterParams(EnvParams())

    def reset(self, key, params: AdapterParams):
        obs, state = self.env.reset(key, params.env)
        return flat(obs), state

    def step(self, key, state, action, params: AdapterParams):
        obs, state, reward, done, info = self.env.step(key, state, action, params.env)
        return flat(obs), state, reward, done, info

    def action_space(self, params=None):
        from gymnax.environments import spaces
        return spaces.Box(-1.0, 1.0, (2,))

    def observation_space(self, params=None):
        from gymnax.environments import spaces
        size = 4 + self.env.num_humans * (2 * (self.env.pred_len + 1) + self.env.pred_len)
        return spaces.Box(-jnp.inf, jnp.inf, (size,))


def environment(predictor: str, humans: int) -> tuple[CrowdNav, EnvParams]:
    model = {"gst": lambda: load_model("pretrained:crowdnav_sj_rand"),
             "cv": lambda: CONSTANT_VELOCITY, "none": lambda: None}[predictor]()
    return CrowdNav.with_predictor(model, humans, Regions("dtaci", 0.1) if model else None)


def ppo(predictor: str, humans: int, timesteps: int, envs: int, steps: int = 64) -> PPO:
    """rejax's PPO over `timesteps` environment steps (one call of its `train`)."""
    from rejax import PPO

    env, params = environment(predictor, humans)
    algo = PPO.create(env=FlatCrowdNav(env), env_params=AdapterParams(params, max_steps(params)),
                      total_timesteps=timesteps, num_envs=envs, num_steps=steps,
                      num_minibatches=4, eval_freq=timesteps, skip_initial_evaluation=True,
                      learning_rate=3e-4, normalize_observations=True)
    # rejax's own evaluation plays 128 full episodes; the measures below replace it.
    return algo.replace(eval_callback=lambda algo, ts, rng: ())


def train(predictor: str = "gst", humans: int = 20, timesteps: int = 100_000, envs: int = 64,
          steps: int = 64, seed: int = 0) -> tuple[PPO, object, dict]:
    """rejax's PPO for `timesteps` environment steps: (the algorithm, its train state, what
    the training took: seconds)."""
    algo = ppo(predictor, humans, timesteps, envs, steps)
    started = time.perf_counter()
    train_state, _ = jax.block_until_ready(jax.jit(algo.train)(jax.random.key(seed)))
    return algo, train_state, {"seconds": time.perf_counter() - started}


def learning_curve(workdir: Path, predictor: str = "gst", humans: int = 20,
                   timesteps: int = 20_000_000, chunk: int = 500_000, envs: int = 64,
                   episodes: int = 100, seed: int = 0) -> list[dict]:
    """PPO `chunk` steps at a time up to `timesteps`, the policy measured after each chunk
    over `episodes` test episodes: the points of <workdir>/curve.jsonl (steps, hours of
    training so far, CrowdNav++'s measures). Continues from <workdir>/state.msgpack."""
    algo = ppo(predictor, humans, chunk, envs)
    step = jax.jit(lambda ts: algo.train(train_state=ts)[0])
    state_path, curve_path = workdir / "state.msgpack", workdir / "curve.jsonl"
    ts = algo.init_state(jax.random.key(seed))
    curve = []
    if state_path.exists():
        ts = _with_keys(ts, serialization.from_bytes(_key_data(ts), state_path.read_bytes()))
        curve = [json.loads(line) for line in curve_path.read_text().splitlines()]
    workdir.mkdir(parents=True, exist_ok=True)
    while int(ts.global_step) < timesteps:
        started = time.perf_counter()
        ts = jax.block_until_ready(step(ts))
        hours = (curve[-1]["hours"] if curve else 0.0) + (time.perf_counter() - started) / 3600
        point = {"steps": int(ts.global_step), "hours": round(hours, 4),
                 **measure(algo, ts, episodes)}
        curve.append(point)
        # The state first, then the point: a crash between them repeats a chunk, never skips.
        temporary = state_path.with_suffix(".tmp")
        temporary.write_bytes(serialization.to_bytes(_key_data(ts)))
        os.replace(temporary, state_path)
        with curve_path.open("a") as f:
            f.write(json.dumps(point) + "\n")
        left = (timesteps - point["steps"]) / point["steps"] * hours
        print(f"{point['steps']:,} steps, {hours:.2f} h: success {point['success']:.3f}, "
              f"collision {point['collision']:.3f}; about {left:.1f} h left", flush=True)
    return curve


def _is_key(leaf) -> bool:
    return hasattr(leaf, "dtype") and jnp.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def _key_data(tree):
    """The tree with its PRNG keys as their raw data (msgpack takes no key arrays)."""
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else x, tree)


def _with_keys(like, plain):
    """`plain` (from `_key_data`) with the keys of `like` wrapped back."""
    return jax.tree.map(lambda template, x: jax.random.wrap_key_data(
        x, impl=jax.random.key_impl(template)) if _is_key(template) else x, like, plain)


def first_reaching(curve: list[dict], success: float = 0.9) -> dict | None:
    """The first point of a learning curve whose success rate reached `success`."""
    return next((point for point in curve if point["success"] >= success), None)


def measure(algo: PPO, train_state, episodes: int, seed: int = 1000) -> dict:
    """CrowdNav++'s measures of the trained policy's mean action over `episodes` episodes."""
    act = algo.make_act(train_state)
    env, params = crowdnav_of(algo)

    def policy(key, planner_state, obs):
        return act(flat(obs), key), planner_state

    episodes_out, _, _ = run_episodes(env, params, policy, jnp.zeros(()), episodes, seed)
    return navigation_measures(episodes_out, params)


def crowdnav_of(algo: PPO) -> tuple[CrowdNav, EnvParams]:
    """The CrowdNav environment and params inside rejax's wrappers of the adapter (its
    observation normalisation wraps the environment)."""
    env = algo.env
    while not isinstance(env, FlatCrowdNav):
        env = env.env
    return env.env, algo.env_params.env


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--predictor", choices=("gst", "cv", "none"), default="gst")
    parser.add_argument("--humans", type=int, default=20)
    parser.add_argument("--timesteps", type=int, default=100_000)
    parser.add_argument("--envs", type=int, default=64)
    parser.add_argument("--episodes", type=int, default=0, help="test episodes measured at the "
                        "end (with --chunk: after each chunk)")
    parser.add_argument("--chunk", type=int, default=0, help="train this many steps at a time, "
                        "a learning curve in --workdir (default: all at once)")
    parser.add_argument("--workdir", type=Path, default=Path("runs/ppo"),
                        help="where --chunk keeps the curve and the state (default: runs/ppo)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    missing = [name for name in ("rejax", "gymnax") if importlib.util.find_spec(name) is None]
    if missing:
        sys.exit(f"error: experiments/ppo_rejax.py needs {' and '.join(missing)}, the rl extra: "
                 'pip install ".[rl]" (from the checkout)')
    if args.chunk:
        curve = learning_curve(args.workdir, args.predictor, args.humans, args.timesteps,
                               args.chunk, args.envs, args.episodes or 100, args.seed)
        print(json.dumps({"points": len(curve), "last": curve[-1],
                          "first_at_0.9_success": first_reaching(curve)}, indent=1))
        return
    algo, train_state, report = train(args.predictor, args.humans, args.timesteps, args.envs,
                                      seed=args.seed)
    if args.episodes:
        report.update(measure(algo, train_state, args.episodes))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
