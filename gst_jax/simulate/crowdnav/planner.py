"""A sampling-based MPC that plans against predicted humans inflated by conformal radii
(ICP's idea: Huang et al., "Interaction-aware conformal prediction", WAFR 2024).

Every step it scores `num_plans` velocity sequences over the prediction horizon, all at once
(vmapped), and takes the first velocity of the cheapest:

- the plans: constant velocities towards 16 headings around the goal's direction at 4
  speeds, standing still, the previous best plan shifted by a step, and random walks of
  heading around the goal's direction at random speeds for the rest;
- the cost: the mean distance to the goal over the plan, plus `collision_weight` per metre
  by which a planned position k steps ahead comes inside the disc of a human's predicted
  position k steps ahead, of radius robot + human radius + that step's conformal radius
  (the observation's `radii`; 0 without regions).

The planner reads only the observation (`environment.Observation`), so the same planner
runs on GST's predictions with their regions, or on constant-velocity ones
(`CrowdNav(model=CONSTANT_VELOCITY)`). The humans' predictions do not react to a plan: GST
reads observed steps only, so a plan cannot enter it (ICP trains a predictor that reads the
robot's plan; that would be num_plans model calls per step instead of one).
"""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp

from gst_jax.simulate.crowdnav.environment import UNDETECTED, Observation


class PlannerState(NamedTuple):
    """The best plan of the last step, (P, 2) velocities, to start from, and the safety
    margin (m) a decision-calibrated planner holds now (`DecisionCalibration`; 0 otherwise)."""

    plan: jax.Array
    margin: jax.Array


@dataclasses.dataclass(frozen=True)
class DecisionCalibration:
    """A safety margin calibrated online to hold a target rate of near misses (conformal
    decision theory: Lekeufack, Angelopoulos, Bajcsy, Jordan & Malik 2023), instead of a disc
    around every predicted position.

    A near miss at a step: a detected human's centre within `near` metres of the robot's
    (CrowdNav++'s robot and largest human radius, 0.3 + 0.5, and its discomfort distance,
    0.25). After each step the margin m, added to every human's clearance in the plans' cost,
    moves by `step` (loss - `target_rate`): up after a near miss, down slowly otherwise, within
    [0, `max_margin`]. Whatever the humans do, the near misses of T steps then average within
    (max_margin + step) / (step T) of the target rate, provided a margin of max_margin keeps
    the robot clear (the update is online gradient descent on the pinball of the rate; the
    bound is its telescoping sum).
    """

    target_rate: float = 0.1
    step: float = 0.05
    max_margin: float = 1.0
    near: float = 1.05

    def update(self, margin: jax.Array, near_miss: jax.Array) -> jax.Array:
        """The next margin after a step with (1) or without (0) a near miss."""
        return jnp.clip(margin + self.step * (near_miss - self.target_rate), 0.0,
                        self.max_margin)

    def near_miss(self, obs: Observation) -> jax.Array:
        """Whether a detected human's centre is within `near` of the robot now."""
        relative = obs.spatial_edges.reshape(obs.spatial_edges.shape[0], -1, 2)[:, 0]
        detected = relative[:, 0] != UNDETECTED
        distance = jnp.linalg.norm(relative, axis=-1)
        return jnp.any(detected & (distance < self.near)).astype(jnp.float32)


@dataclasses.dataclass(frozen=True)
class SamplingMPC:
    """num_plans: velocity sequences scored per step; horizon: their length (the predicted
    steps P); step_s: seconds per step; max_speed: the robot's (m/s); clearance: the robot's
    radius + the largest human's (CrowdNav++: 0.3 + 0.5; the observation has no radii);
    collision_weight: cost per metre inside a disc; heading_noise: radians per step of the
    random walks; calibration: a safety margin calibrated online (`DecisionCalibration`),
    added to every human's clearance, or None."""

    num_plans: int = 256
    horizon: int = 5
    step_s: float = 0.25
    max_speed: float = 1.0
    clearance: float = 0.8
    collision_weight: float = 100.0
    heading_noise: float = 0.5
    calibration: DecisionCalibration | None = None
    # 16 headings x 4 speeds, standing still, the last best plan shifted.
    fixed_plans: ClassVar[int] = 66

    def init(self) -> PlannerState:
        return PlannerState(jnp.zeros((self.horizon, 2)), jnp.zeros(()))

    def plans(self, key: jax.Array, toward_goal: jax.Array, previous: jax.Array) -> jax.Array:
        """(num_plans, P, 2) candidate velocity sequences."""
        heading = jnp.arctan2(toward_goal[1], toward_goal[0])
        grid_heading = heading + jnp.linspace(-math.pi, math.pi, 16, endpoint=False)
        speeds = self.max_speed * jnp.array([0.25, 0.5, 0.75, 1.0])
        angle, speed = jnp.repeat(grid_heading, 4), jnp.tile(speeds, 16)
        constant = speed[:, None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)  # (64, 2)
        constant = jnp.broadcast_to(constant[:, None], (64, self.horizon, 2))
        still = jnp.zeros((1, self.horizon, 2))
        shifted = jnp.concatenate([previous[1:], previous[-1:]])[None]
        fixed = jnp.concatenate([constant, still, shifted])
        count = self.num_plans - fixed.shape[0]
        turn_key, offset_key, speed_key = jax.random.split(key, 3)
        turns = jnp.cumsum(self.heading_noise * jax.random.normal(
            turn_key, (count, self.horizon)), axis=1)
        walk_heading = heading + turns + jax.random.uniform(
            offset_key, (count, 1), minval=-math.pi / 2, maxval=math.pi / 2)
        walk_speed = self.max_speed * jax.random.uniform(speed_key, (count, 1))
        walks = walk_speed[..., None] * jnp.stack([jnp.cos(walk_heading),
                                                   jnp.sin(walk_heading)], -1)
        return jnp.concatenate([fixed, walks])

    def cost(self, plan: jax.Array, robot: jax.Array, goal: jax.Array,
             humans: jax.Array, radii: jax.Array, present: jax.Array) -> jax.Array:
        """One plan's cost: plan (P, 2) velocities from `robot` (2,); humans (H, P, 2)
        predicted positions, radii (H, P), present (H,)."""
        path = robot + jnp.cumsum(plan, axis=0) * self.step_s                     # (P, 2)
        progress = jnp.linalg.norm(path - goal, axis=-1).mean()
        distance = jnp.linalg.norm(path[None] - humans, axis=-1)                 # (H, P)
        inside = jnp.maximum(self.clearance + radii - distance, 0.0) * present[:, None]
        return progress + self.collision_weight * inside.sum()

    def __call__(self, key: jax.Array, state: PlannerState, obs: Observation
                 ) -> tuple[jax.Array, PlannerState]:
        """The velocity (2,) to apply now, and the planner's next state."""
        robot, goal = obs.robot_node[:2], obs.robot_node[3:5]
        relative = obs.spatial_edges.reshape(obs.spatial_edges.shape[0], -1, 2)  # (H, 1+P, 2)
        humans = robot + relative[:, 1:]
        present = relative[:, 0, 0] != UNDETECTED          # rows of undetected humans: 15
        margin, radii = state.margin, obs.radii
        if self.calibration is not None:      # the last step's outcome is seen now
            margin = self.calibration.update(margin, self.calibration.near_miss(obs))
            radii = radii + margin
        plans = self.plans(key, goal - robot, state.plan)
        costs = jax.vmap(self.cost, in_axes=(0, None, None, None, None, None))(
            plans, robot, goal, humans, radii, present)
        best = plans[jnp.argmin(costs)]
        return best[0], PlannerState(best, margin)
