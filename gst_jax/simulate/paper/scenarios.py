"""The robot/human scenarios of the paper's Fig. 5, as initial states (numpy only), on the
time grid of the model that drives them."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from gst_jax.config import TimeGrid


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Initial state of A agents (agent 0 = robot); all arrays numpy.

    start (A, 2) position at step 0; velocity (A, 2) m/s of the scripted straight line (also
    the history of grid.obs_len steps before step 0); detected_from (A,) step from which an
    agent is seen (0 = from the start, history included); goal (2,) the robot's goal; grid:
    the steps (those of the model that drives the agents); duration_s: how long it runs (10 s:
    25 of the paper's 0.4 s steps).
    """

    name: str
    start: np.ndarray
    velocity: np.ndarray
    detected_from: np.ndarray
    goal: np.ndarray
    grid: TimeGrid = TimeGrid()
    duration_s: float = 10.0

    @property
    def steps(self) -> int:
        return round(self.duration_s / self.grid.step_s)


def late_crossing(grid: TimeGrid = TimeGrid(), delay_s: float = 1.6,
                  speed: float = 1.2) -> Scenario:
    """(a) A human enters the robot's field of view `delay_s` late, walking into its path."""
    start = np.array([[0.0, 0.0], [6.0, -6.0]])       # both reach (6, 0) after 5 s
    velocity = np.array([[speed, 0.0], [0.0, speed]])
    return Scenario("a_late_crossing", start, velocity,
                    np.array([0, round(delay_s / grid.step_s)]), np.array([12.0, 0.0]), grid)


def boundary_wanderers(grid: TimeGrid = TimeGrid(), num_wanderers: int = 6, speed: float = 1.2,
                       seed: int = 0) -> Scenario:
    """(b) Six humans wander near the boundary while one walks straight at the robot."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 2 * np.pi, num_wanderers, endpoint=False)
    ring = 6.0 + np.stack([7 * np.cos(angles), 7 * np.sin(angles)], -1)
    tangent = (0.5 * np.stack([-np.sin(angles), np.cos(angles)], -1)
               + rng.normal(0, 0.05, (num_wanderers, 2)))
    start = np.concatenate([[[0.0, 0.0], [12.0, 0.0]], ring])
    velocity = np.concatenate([[[speed, 0.0], [-speed, 0.0]], tangent])
    return Scenario("b_boundary_wanderers", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]), grid)


def intersection(grid: TimeGrid = TimeGrid(), num_humans: int = 3,
                 speed: float = 1.2) -> Scenario:
    """(c) The robot and a file of humans meet at an intersection."""
    humans = np.stack([np.full(num_humans, 6.0), -6.0 - 1.2 * np.arange(num_humans)], -1)
    start = np.concatenate([[[0.0, 0.0]], humans])
    velocity = np.concatenate([[[speed, 0.0]], np.tile([[0.0, speed]], (num_humans, 1))])
    return Scenario("c_intersection", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]), grid)


def oncoming_group(grid: TimeGrid = TimeGrid(), group_size: int = 8,
                   speed: float = 1.2) -> Scenario:
    """(d) The robot moving right meets a group of eight humans moving left."""
    rows, cols = 2, (group_size + 1) // 2
    group = np.array([[12.0 + 0.8 * c, -0.6 + 1.2 * r] for r in range(rows)
                      for c in range(cols)])[:group_size]
    start = np.concatenate([[[0.0, 0.0]], group])
    velocity = np.concatenate([[[speed, 0.0]], np.tile([[-speed, 0.0]], (group_size, 1))])
    return Scenario("d_oncoming_group", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]), grid)


SCENARIOS: dict[str, Callable[[TimeGrid], Scenario]] = {
    "a": late_crossing, "b": boundary_wanderers, "c": intersection, "d": oncoming_group}
