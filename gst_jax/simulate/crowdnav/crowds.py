"""Training crowds from the navigation task's own humans: what a planner's predictor would see.

A predictor trained where it is used learns the environment's own motion (`environment.CrowdNav`'s
exact ORCA and social force, with and without its shifts, 10 to 35 humans, reactive or not),
not a stand-in's. Each recorded episode plays the task from its reset for the whole 50 s,
the robot driven by the sampling MPC against constant-velocity predictions (the study's
baseline, so reactive humans give way to a robot that moves as it would), and keeps every
position the robot detected, at the task's 0.25 s steps. An episode does not stop when the
robot arrives or collides: the humans walk on.

Written in the project's `frame ped x y` format, one file per episode, named by its
condition: frame ids count steps from the reset (4 per second); a human replaced by a new one
(it reached its goal) takes a new id, so ids name people, not slots. Episodes are seeded from
`seed` as the study's are from theirs (episode i from the i-th key of split(key(seed), count)),
so a seed other than the study's 1000 gives other episodes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.progress import Progress
from gst_jax.simulate.crowdnav.environment import (
    CONSTANT_VELOCITY,
    NO_SHIFT,
    ORCA,
    POLICY_SHIFT,
    SOCIAL_FORCE,
    SPEED_SHIFT,
    CrowdNav,
    EnvParams,
    detected_humans,
)
from gst_jax.simulate.crowdnav.planner import SamplingMPC


@dataclasses.dataclass(frozen=True)
class Condition:
    """How one recorded crowd walks (`CrowdNav`'s human_policy, reactive, num_humans,
    shift)."""

    human_policy: str = ORCA
    reactive: bool = False
    num_humans: int = 20
    shift: str = NO_SHIFT

    @property
    def name(self) -> str:
        """e.g. orca-humans20, social_force-reactive-humans35-shiftspeed."""
        return "-".join([self.human_policy, *(["reactive"] if self.reactive else []),
                         f"humans{self.num_humans}",
                         *([f"shift{self.shift}"] if self.shift != NO_SHIFT else [])])


# The mix a planner's predictor trains on: both motion models, every shift that applies to
# them, humans who ignore the robot and humans who give way to it, 10, 20 and 35 of them.
MIX = tuple(Condition(policy, reactive, count, shift)
            for policy, shifts in ((ORCA, (NO_SHIFT, SPEED_SHIFT, POLICY_SHIFT)),
                                   (SOCIAL_FORCE, (NO_SHIFT, SPEED_SHIFT)))
            for shift in shifts for reactive in (False, True) for count in (10, 20, 35))


def record_episodes(condition: Condition, count: int, seed: int, params: EnvParams = EnvParams(),
                    steps: int | None = None) -> dict[str, np.ndarray]:
    """`count` episodes of `condition` from their resets, `steps` steps each (default: to the
    end of the 50 s), in one program: human positions (E, S+1, H, 2) and which the robot
    detects (E, S+1, H) at the reset and after each of S steps, and which slots took a new
    human at each step (E, S, H)."""
    env = CrowdNav(condition.num_humans, CONSTANT_VELOCITY, human_policy=condition.human_policy,
                   reactive=condition.reactive, shift=condition.shift)
    planner = SamplingMPC(horizon=env.pred_len, step_s=params.step_s)
    steps = steps or round(params.time_limit_s / params.step_s) - 1

    def episode(key):
        reset_key, run_key = jax.random.split(key)
        obs, state = env.reset(reset_key, params)

        def step(carry, key):
            obs, state, plan = carry
            plan_key, env_key = jax.random.split(key)
            action, plan = planner(plan_key, plan, obs)
            obs, state, _, _, info = env.step_env(env_key, state, action, params)
            return (obs, state, plan), (state.human_position, detected_humans(state, params),
                                        info["replaced"])

        _, (positions, detected, replaced) = jax.lax.scan(
            step, (obs, state, planner.init()), jax.random.split(run_key, steps))
        return {"positions": jnp.concatenate([state.human_position[None], positions]),
                "detected": jnp.concatenate([detected_humans(state, params)[None], detected]),
                "replaced": replaced}

    keys = jax.random.split(jax.random.key(seed), count)
    return jax.tree.map(np.asarray, jax.jit(jax.vmap(episode))(keys))


def person_ids(replaced: np.ndarray) -> np.ndarray:
    """(S+1, H) the id of the person in each slot at each time: slot k's first person is k,
    and each replacement takes the next unused id."""
    slots = replaced.shape[1]
    ids = np.empty((replaced.shape[0] + 1, slots), np.int64)
    ids[0] = np.arange(slots)
    next_id = slots
    for t, new in enumerate(replaced):
        ids[t + 1] = ids[t]
        for k in np.flatnonzero(new):
            ids[t + 1, k], next_id = next_id, next_id + 1
    return ids


def crowd_rows(positions: np.ndarray, detected: np.ndarray, ids: np.ndarray) -> list[str]:
    """`frame ped x y` rows of the detected positions (S+1, H, 2), frame ids counting steps,
    ped ids from `ids` (S+1, H)."""
    return [f"{t} {ids[t, k]} {positions[t, k, 0]:.4f} {positions[t, k, 1]:.4f}"
            for t, k in zip(*np.nonzero(detected))]


def write_crowds(out: Path, conditions: tuple[Condition, ...], episodes: int, seed: int,
                 progress: Progress | None = None, steps: int | None = None) -> list[Path]:
    """`episodes` recorded episodes of each condition written to out/CONDITION-seedSEED-
    episodeI.txt (condition i's episodes from seed + i, so that adding a condition leaves the
    others' files as they were), `steps` steps each (default: to the end of the 50 s); the
    files written."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, condition in enumerate(conditions):
        record = record_episodes(condition, episodes, seed + i, steps=steps)
        for e in range(episodes):
            path = out / f"{condition.name}-seed{seed + i}-episode{e}.txt"
            rows = crowd_rows(record["positions"][e], record["detected"][e],
                              person_ids(record["replaced"][e]))
            path.write_text("\n".join(rows) + "\n")
            written.append(path)
        if progress:
            progress.line(f"{condition.name}: {episodes} episodes ({i + 1}/{len(conditions)})")
    return written
