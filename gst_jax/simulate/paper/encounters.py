"""Randomized encounters: a robot against a group of people, thousands of episodes per model
in one jitted, vmapped program, and whether the robot freezes.

Every episode (14 s): the robot starts at (0, 0) walking at 1.2 m/s towards its goal
(12, 0), 10 s away at that speed (its history is that straight line); a group of k = 2..10
people (uniform) meets its path at a point m = (U(4, 8), U(-1, 1)) m about when the robot gets
there (within U(-1, 1) s), in one of the paper's four kinds of encounter (Fig. 5 a-d, uniform):

- crossing: the group walks across the path at U(45, 135) degrees, from either side;
- late: the same, but the whole group is detected only U(1, 3) s after the start (a);
- oncoming: the group walks against the robot, heading 180 +- U(0, 20) degrees (d);
- wander: the people stroll near m at U(0, 0.5) m/s in random directions (b).

A group walks at one speed U(0.8, 1.6) m/s (each person +- 0.1), in rows of up to three
across its heading, U(0.6, 1.2) m apart, jittered by 0.1 m. As in `loop.py`, every detected
agent, the robot included, moves by the model's first predicted displacement; people not
yet detected walk their scripted line. Episodes have 11 agent slots; the slots of a smaller
group are never detected and stay far away.

What counts, fixed before any model was run (`measures.freezing_or_u_turn`, the
single-scenario study's detector): the robot freezes when its progress towards the goal
stays below 0.1 m/s for more than 2 s, or turns back when its heading turns more than 120
degrees from its first; a collision is a person's centre within 0.3 m of the robot's; it
arrives when it comes within 0.5 m of its goal (time to goal: the first such step).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import TimeGrid
from gst_jax.simulate.agents.predicted import StepModel
from gst_jax.simulate.paper.loop import MODEL_HUMANS, episode
from gst_jax.simulate.paper.measures import robot_measures
from gst_jax.simulate.paper.scenarios import Scenario

KINDS = ("crossing", "late", "oncoming", "wander")
GOAL = np.array([12.0, 0.0])
ROBOT_SPEED = 1.2
MAX_PEOPLE = 10
ARRIVAL_DISTANCE = 0.5


@dataclasses.dataclass(frozen=True)
class Encounters:
    """E episodes of A = 1 + MAX_PEOPLE agent slots (agent 0 the robot): start (E, A, 2),
    velocity (E, A, 2) m/s, detected_from (E, A) steps (past the episode: an empty slot),
    people (E,) the group's size, kind (E,) an index into KINDS."""

    start: np.ndarray
    velocity: np.ndarray
    detected_from: np.ndarray
    people: np.ndarray
    kind: np.ndarray
    grid: TimeGrid
    duration_s: float

    @property
    def steps(self) -> int:
        return round(self.duration_s / self.grid.step_s)

    def scenario(self, index: int) -> Scenario:
        """Episode `index` as a Scenario (its people only)."""
        agents = 1 + int(self.people[index])
        return Scenario(f"encounter-{index}-{KINDS[self.kind[index]]}",
                        self.start[index, :agents], self.velocity[index, :agents],
                        self.detected_from[index, :agents], GOAL, self.grid, self.duration_s)


def sample_encounters(count: int, seed: int = 0, grid: TimeGrid = TimeGrid(),
                      duration_s: float = 14.0) -> Encounters:
    """`count` random encounters (module docstring), the same for a seed."""
    rng = np.random.default_rng(seed)
    steps = round(duration_s / grid.step_s)
    agents = 1 + MAX_PEOPLE
    start = np.zeros((count, agents, 2))
    velocity = np.zeros((count, agents, 2))
    detected_from = np.full((count, agents), steps + 1)
    people = rng.integers(2, MAX_PEOPLE + 1, count)
    kind = rng.integers(0, len(KINDS), count)
    velocity[:, 0] = [ROBOT_SPEED, 0.0]
    detected_from[:, 0] = 0
    for e in range(count):
        k, name = people[e], KINDS[kind[e]]
        meet = np.array([rng.uniform(4, 8), rng.uniform(-1, 1)])
        meet_s = meet[0] / ROBOT_SPEED + rng.uniform(-1, 1)
        if name == "oncoming":
            heading = np.pi + np.radians(rng.uniform(-20, 20))
        else:
            heading = np.radians(rng.uniform(45, 135)) * rng.choice([-1, 1])
        along = np.array([np.cos(heading), np.sin(heading)])
        across = np.array([-along[1], along[0]])
        spacing = rng.uniform(0.6, 1.2)
        row, column = np.divmod(np.arange(k), 3)
        offsets = (-row[:, None] * along + (column - (min(k, 3) - 1) / 2)[:, None] * across)
        offsets = offsets * spacing + rng.normal(0, 0.1, (k, 2))
        if name == "wander":
            angles = rng.uniform(0, 2 * np.pi, k)
            walk = rng.uniform(0, 0.5, (k, 1)) * np.stack([np.cos(angles), np.sin(angles)], -1)
        else:
            walk = along * (rng.uniform(0.8, 1.6) + rng.uniform(-0.1, 0.1, (k, 1)))
        start[e, 1:k + 1] = meet + offsets - walk * meet_s
        velocity[e, 1:k + 1] = walk
        detected_from[e, 1:k + 1] = round(rng.uniform(1, 3) / grid.step_s) \
            if name == "late" else 0
    # Empty slots: far from everyone, still, never detected.
    empty = np.arange(agents)[None] > people[:, None]
    start[empty] = 1e3 + 10.0 * np.argwhere(empty)[:, 1:2]
    return Encounters(start, velocity, detected_from, people, kind, grid, duration_s)


def run_encounters(model: StepModel, encounters: Encounters, key: jax.Array,
                   humans: str = MODEL_HUMANS) -> tuple[np.ndarray, float, float]:
    """Positions (E, steps + 1, A, 2) of every episode, one jitted program over all of them
    (each its own key), and the seconds it took to compile and to run; the people moved as
    `humans` says (`loop.episode`)."""
    grid = encounters.grid
    run = jax.jit(jax.vmap(functools.partial(episode, model, steps=encounters.steps,
                                             humans=humans,
                                             obs_len=grid.obs_len, step_s=grid.step_s)))
    args = (jnp.asarray(encounters.start, jnp.float32),
            jnp.asarray(encounters.velocity, jnp.float32),
            jnp.asarray(encounters.detected_from), jax.random.split(key, len(encounters.people)))
    started = time.perf_counter()
    compiled = run.lower(*args).compile()
    compiled_at = time.perf_counter()
    positions = np.asarray(compiled(*args))
    return positions, compiled_at - started, time.perf_counter() - compiled_at


def episode_measures(positions: np.ndarray, encounters: Encounters) -> list[dict]:
    """Per episode: `robot_measures` of its people, whether it collided and arrived, and
    its time to goal (s; None without arrival)."""
    rows = []
    for index, run in enumerate(positions):
        scenario = encounters.scenario(index)
        agents = 1 + int(encounters.people[index])
        row = robot_measures(run[:, :agents], scenario)
        near_goal = np.linalg.norm(run[:, 0] - GOAL, axis=-1) <= ARRIVAL_DISTANCE
        row.update(kind=KINDS[encounters.kind[index]], people=agents - 1,
                   collided=row["collision_steps"] > 0, arrived=bool(near_goal.any()),
                   time_to_goal_s=float(np.argmax(near_goal) * encounters.grid.step_s)
                   if near_goal.any() else None)
        rows.append(row)
    return rows


def summarize(rows: list[dict]) -> dict:
    """Rates with Wilson 95 % intervals, means with normal 95 % intervals: (value, low, high)."""
    count = len(rows)

    def rate(key):
        hits = sum(bool(r[key]) for r in rows)
        return wilson(hits, count)

    def mean(values):
        values = np.asarray([v for v in values if v is not None and math.isfinite(v)])
        if not len(values):
            return (None, None, None)
        half = 1.96 * values.std(ddof=1) / math.sqrt(len(values)) if len(values) > 1 else 0.0
        return (float(values.mean()), float(values.mean() - half), float(values.mean() + half))

    return {"episodes": count, "freezing_or_u_turn": rate("freezing_or_u_turn"),
            "frozen": rate("frozen"), "u_turn": rate("u_turn"), "collided": rate("collided"),
            "arrived": rate("arrived"),
            "time_to_goal_s": mean([r["time_to_goal_s"] for r in rows]),
            "progress": mean([r["progress"] for r in rows]),
            "path_length_ratio": mean([r["path_length_ratio"] for r in rows])}


def wilson(hits: int, count: int, z: float = 1.96) -> tuple[float, float, float]:
    """A proportion and its Wilson score interval."""
    if count == 0:
        return (float("nan"),) * 3
    p = hits / count
    centre = (p + z * z / (2 * count)) / (1 + z * z / count)
    half = z * math.sqrt(p * (1 - p) / count + z * z / (4 * count * count)) / (1 + z * z / count)
    return (p, max(centre - half, 0.0), min(centre + half, 1.0))


def format_encounters(summaries: dict[str, dict]) -> str:
    """The summaries as a markdown table: value [95 % interval]."""
    columns = ["freezing_or_u_turn", "collided", "arrived", "time_to_goal_s",
               "path_length_ratio"]

    def cell(triple):
        value, low, high = triple
        return "-" if value is None else f"{value:.3f} [{low:.3f}, {high:.3f}]"

    lines = ["| model | episodes/s | " + " | ".join(columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for label, summary in summaries.items():
        lines.append(f"| {label} | {summary['episodes_per_s']:.0f} | "
                     + " | ".join(cell(summary[c]) for c in columns) + " |")
    return "\n".join(lines)
