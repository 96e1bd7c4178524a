"""Simulated crowds for training a planner's predictor: ORCA-like humans in CrowdNav++'s arena.

CrowdNav++ trains its predictor on its own simulator's humans: 20 of them in a circle of
radius 6 m, each walking at its preferred speed towards a goal across the circle, avoiding
the others with ORCA, a new goal once one is reached, seen by a robot whose sensor reaches
5 m. This is a numpy stand-in with the same shape: reciprocal velocity obstacles by
sampling (each human picks, among candidate velocities, the one closest to its preferred
velocity that its neighbours' share of the avoidance keeps clear of collisions for a few
seconds), observed from the circle's centre, so that humans near the rim enter and leave
view: partially detected pedestrians, as a robot sees them. numpy only.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class CrowdConfig:
    """One simulated crowd.

    Attributes:
      num_humans: humans in the arena (CrowdNav++: 20).
      step_s: seconds per step (CrowdNav++: 0.25).
      duration_s: length of the episode.
      arena_radius: humans start and find goals on a circle of this radius (m).
      sensor_range: humans farther than this from the centre are not detected (m).
      human_radius: the disc two humans keep apart (m).
      preferred_speed: (low, high) range of the humans' preferred speeds (m/s).
      time_horizon: seconds ahead within which a candidate velocity must be collision free.
      avoidance: weight of the penalty `avoidance / time to collision` of a candidate that
        collides within the horizon, against its distance (m/s) to the preferred velocity.
      candidates: sampled velocities per human and step.
    """

    num_humans: int = 20
    step_s: float = 0.25
    duration_s: float = 50.0
    arena_radius: float = 6.0
    sensor_range: float = 5.0
    human_radius: float = 0.3
    preferred_speed: tuple[float, float] = (0.5, 1.5)
    time_horizon: float = 5.0
    avoidance: float = 6.0
    candidates: int = 100


def simulate_crowd(config: CrowdConfig, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Positions (S+1, H, 2) of one episode and whether each human is detected (S+1, H)."""
    rng = np.random.default_rng(seed)
    h = config.num_humans
    speed = rng.uniform(*config.preferred_speed, h)
    position = _points_on_circle(rng, h, config.arena_radius, config.human_radius)
    goal = -position + rng.normal(0.0, 0.5, (h, 2))            # across the circle
    velocity = np.zeros((h, 2))
    steps = [position]
    for _ in range(round(config.duration_s / config.step_s)):
        arrived = np.linalg.norm(goal - position, axis=-1) < config.human_radius
        if arrived.any():
            goal[arrived] = _points_on_circle(rng, int(arrived.sum()), config.arena_radius, 0.0)
        velocity = _avoiding_velocity(position, velocity, goal, speed, config, rng)
        position = position + velocity * config.step_s
        steps.append(position)
    positions = np.stack(steps)
    return positions, np.linalg.norm(positions, axis=-1) <= config.sensor_range


def _points_on_circle(rng, count: int, radius: float, spacing: float) -> np.ndarray:
    """`count` points on the circle, at least 2 * spacing apart (start positions)."""
    points = np.zeros((0, 2))
    while len(points) < count:
        angle = rng.uniform(0.0, 2 * np.pi)
        point = radius * np.array([np.cos(angle), np.sin(angle)])
        if not len(points) or np.linalg.norm(points - point, axis=-1).min() > 2 * spacing:
            points = np.concatenate([points, point[None]])
    return points


def _avoiding_velocity(position, velocity, goal, speed, config: CrowdConfig, rng) -> np.ndarray:
    """Each human's next velocity (H, 2): among sampled candidates (and its preferred
    velocity), the one that minimises the distance to the preferred velocity plus a penalty
    for colliding within the time horizon, judged reciprocally (RVO: each of a pair takes half
    of the avoidance, so the relative velocity is 2 v - v_self - v_other)."""
    to_goal = goal - position
    distance = np.linalg.norm(to_goal, axis=-1, keepdims=True)
    preferred = to_goal / np.maximum(distance, 1e-9) * np.minimum(speed[:, None], distance
                                                                   / config.step_s)
    h, m = len(position), config.candidates
    angle = rng.uniform(0.0, 2 * np.pi, (h, m))
    magnitude = speed[:, None] * np.sqrt(rng.uniform(0.0, 1.0, (h, m)))
    candidates = np.concatenate([preferred[:, None], np.zeros((h, 1, 2)), np.stack(
        [magnitude * np.cos(angle), magnitude * np.sin(angle)], -1)], axis=1)   # (H, M+2, 2)

    relative_position = position[None, :, :] - position[:, None, :]           # (H, H, 2) j - i
    relative_velocity = (2 * candidates[:, :, None, :] - velocity[:, None, None, :]
                         - velocity[None, None, :, :])                      # (H, M+2, H, 2)
    time = _time_to_collision(relative_position[:, None], relative_velocity,
                              2 * config.human_radius)                       # (H, M+2, H)
    time[np.arange(h), :, np.arange(h)] = np.inf                             # not oneself
    first = time.min(axis=-1)
    penalty = np.where(first < config.time_horizon, config.avoidance / np.maximum(first, 1e-3),
                       0.0)
    cost = np.linalg.norm(candidates - preferred[:, None], axis=-1) + penalty
    chosen = candidates[np.arange(h), np.argmin(cost, axis=-1)]
    return chosen + rng.normal(0.0, 0.02, chosen.shape)       # humans are not exact


def _time_to_collision(offset: np.ndarray, velocity: np.ndarray, radius: float) -> np.ndarray:
    """Seconds until two discs touch (centres `radius` apart): the first moves at `velocity`
    relative to the second, which sits at `offset` from it (..., 2). inf if never; discs that
    overlap already: 0 while they close in, inf once they separate."""
    a = np.sum(velocity ** 2, axis=-1)
    b = -2 * np.sum(offset * velocity, axis=-1)
    c = np.sum(offset ** 2, axis=-1) - radius ** 2
    discriminant = b ** 2 - 4 * a * c
    root = (-b - np.sqrt(np.maximum(discriminant, 0.0))) / np.maximum(2 * a, 1e-12)
    time = np.where((discriminant > 0) & (root >= 0), root, np.inf)
    return np.where(c <= 0, np.where(b < 0, 0.0, np.inf), time)


def crowd_rows(positions: np.ndarray, detected: np.ndarray) -> list[str]:
    """`frame ped x y` rows of the detected positions: frame ids count steps (0, 1, ...)."""
    return [f"{t} {k} {positions[t, k, 0]:.4f} {positions[t, k, 1]:.4f}"
            for t, k in zip(*np.nonzero(detected))]
