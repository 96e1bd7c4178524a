"""What a simulated run tells about the robot: safety, efficiency, freezing and U-turns."""

from __future__ import annotations

import numpy as np

from gst_jax.simulate.paper.scenarios import Scenario

# A robot collides with a human whose centre comes closer than this (metres): a robot of
# 0.3 m radius and a point human. Not `metrics.COLLISION_DISTANCE`, which is between two
# pedestrians' predicted positions.
ROBOT_COLLISION_DISTANCE = 0.3


def robot_measures(positions: np.ndarray, scenario: Scenario) -> dict:
    """Robot safety and efficiency, and the freezing / U-turn detector. positions (S+1, A, 2)."""
    robot, humans = positions[:, 0], positions[:, 1:]
    distances = np.linalg.norm(humans - robot[:, None], axis=-1)              # (S+1, H)
    goal = np.asarray(scenario.goal, float)
    to_goal = np.linalg.norm(goal - robot, axis=-1)
    # The predictor knows no goal, so the robot walks on past it: judge it up to its closest
    # approach to the goal.
    arrival = int(np.argmin(to_goal))
    steps = np.diff(robot[:arrival + 1], axis=0)
    path_length = float(np.linalg.norm(steps, axis=-1).sum())
    straight = float(np.linalg.norm(robot[arrival] - robot[0]))
    return {
        "min_distance_m": float(distances.min()) if distances.size else float("inf"),
        "collision_steps": int(np.sum(distances.min(axis=1) < ROBOT_COLLISION_DISTANCE))
        if distances.size else 0,
        "progress": float((to_goal[0] - to_goal[arrival]) / to_goal[0]),
        "path_length_ratio": path_length / straight if straight > 1e-6 else float("inf"),
        **freezing_or_u_turn(robot[:arrival + 1], goal, scenario.grid.step_s),
    }


def freezing_or_u_turn(robot: np.ndarray, goal: np.ndarray, step_s: float, *,
                       reverse_deg: float = 120.0, stall_s: float = 2.0,
                       stall_speed: float = 0.1) -> dict:
    """U-turn: the robot's heading turns by more than `reverse_deg` from its initial heading.
    Freezing: progress toward the goal below `stall_speed` m/s for more than `stall_s`.
    robot (S+1, 2) positions `step_s` seconds apart."""
    steps = np.diff(robot, axis=0)
    if not len(steps):
        return {"u_turn": False, "frozen": False, "freezing_or_u_turn": False}
    moving = np.linalg.norm(steps, axis=-1) > 1e-6
    headings = np.arctan2(steps[:, 1], steps[:, 0])
    initial = headings[np.argmax(moving)] if moving.any() else 0.0
    turn = np.degrees(np.abs(np.angle(np.exp(1j * (headings - initial)))))
    u_turn = bool(np.any(moving & (turn > reverse_deg)))
    direction = (goal - robot[:-1]) / np.maximum(
        np.linalg.norm(goal - robot[:-1], axis=-1, keepdims=True), 1e-9)
    progress_speed = np.sum(steps * direction, axis=-1) / step_s
    stalled = progress_speed < stall_speed
    longest, run = 0, 0
    for s in stalled:
        run = run + 1 if s else 0
        longest = max(longest, run)
    frozen = longest * step_s > stall_s
    return {"u_turn": u_turn, "frozen": bool(frozen), "freezing_or_u_turn": u_turn or bool(frozen)}
