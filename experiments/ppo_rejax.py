"""Train a robot's policy with PPO from rejax (a maintained JAX RL library) in CrowdNav++'s
task with GST in the loop: gst_jax.simulate.environment.CrowdNav as it is, behind the thin
adapter below (a flat observation, gymnax's spaces, rejax's max_steps_in_episode).

    pip install ".[rl]"            # rejax and gymnax: the rl extra
    python experiments/ppo_rejax.py --timesteps 2000000 --envs 64

The whole training (environments, GST, PPO's updates) is one jitted program. This is the
example, not CrowdNav++'s RL training (its recurrent attention policy over 20 M steps): it
reports the mean return of the last rollouts and, with --episodes, CrowdNav++'s measures of
the trained policy (`gst_jax.simulate.navigation`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import sys
import time
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
from flax import struct

from gst_jax.runs import load_model
from gst_jax.simulate.environment import CONSTANT_VELOCITY, CrowdNav, EnvParams, Observation
from gst_jax.simulate.navigation import max_steps, navigation_measures, run_episodes
from gst_jax.stream import Regions

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


def train(predictor: str = "gst", humans: int = 20, timesteps: int = 100_000, envs: int = 64,
          steps: int = 64, seed: int = 0) -> tuple[PPO, object, dict]:
    """rejax's PPO for `timesteps` environment steps: (the algorithm, its train state, what
    the training showed: the mean reward per step over its last rollout and the seconds)."""
    from rejax import PPO

    env, params = environment(predictor, humans)
    algo = PPO.create(env=FlatCrowdNav(env), env_params=AdapterParams(params, max_steps(params)),
                      total_timesteps=timesteps, num_envs=envs, num_steps=steps,
                      num_minibatches=4, eval_freq=timesteps, skip_initial_evaluation=True,
                      learning_rate=3e-4, normalize_observations=True)
    # rejax's own evaluation plays 128 full episodes; the measures below replace it.
    algo = algo.replace(eval_callback=lambda algo, ts, rng: ())
    started = time.perf_counter()
    train_state, _ = jax.block_until_ready(jax.jit(algo.train)(jax.random.key(seed)))
    return algo, train_state, {"seconds": time.perf_counter() - started}


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
    parser.add_argument("--episodes", type=int, default=0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    missing = [name for name in ("rejax", "gymnax") if importlib.util.find_spec(name) is None]
    if missing:
        sys.exit(f"error: experiments/ppo_rejax.py needs {' and '.join(missing)}, the rl extra: "
                 'pip install ".[rl]" (from the checkout)')
    algo, train_state, report = train(args.predictor, args.humans, args.timesteps, args.envs,
                                      seed=args.seed)
    if args.episodes:
        report.update(measure(algo, train_state, args.episodes))
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
