"""A CrowdNav episode as an animated GIF."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter

from gst_jax.figures import plt


def animate_navigation(robot: np.ndarray, humans: np.ndarray, goal: np.ndarray, steps: int,
                       path: Path, title: str, step_s: float = 0.25) -> Path:
    """Animated GIF of a CrowdNav episode (`navigation.run_episodes`' arrays of one episode:
    robot (S+1, 2), humans (S+1, H, 2)) up to its last step, at 2x real time: the robot's
    trail and disc in red, the humans in blue (discs of their mean radius, 0.4 m), the
    sensor's reach (5 m beyond the robot's surface) in grey."""
    robot, humans = robot[:steps + 1], humans[:steps + 1]
    fig, ax = plt.subplots(figsize=(3.6, 3.6))
    ax.set_xlim(-10, 10)
    ax.set_ylim(-10, 10)
    ax.set_aspect("equal")
    ax.plot(*goal, "*", color="tab:red", ms=10)
    ax.set_title(title, fontsize=7)
    ax.tick_params(labelsize=6)
    trail = ax.plot([], [], "-", color="tab:red", lw=1.0)[0]
    body = plt.Circle(robot[0], 0.3, color="tab:red")
    sensor = plt.Circle(robot[0], 5.3, color="0.6", fill=False, lw=0.6, ls="--")
    people = [plt.Circle(xy, 0.4, color="tab:blue") for xy in humans[0]]
    for patch in [body, sensor, *people]:
        ax.add_patch(patch)

    def draw(t: int) -> list:
        trail.set_data(robot[:t + 1, 0], robot[:t + 1, 1])
        body.center = sensor.center = robot[t]
        for person, xy in zip(people, humans[t]):
            person.center = xy
        return [trail, body, sensor, *people]

    path.parent.mkdir(parents=True, exist_ok=True)
    # Written in a folder beside it, then renamed: an interrupt (which Pillow's cleanup, for
    # errors only, lets through) leaves no empty or cut GIF under the name a rerun looks for.
    # Pillow takes the format from the name, so the GIF keeps its own name in that folder.
    partial = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent))
    try:
        FuncAnimation(fig, draw, frames=len(robot), blit=True).save(
            # matplotlib's stubs want an int; a GIF takes any rate (frames 1000 / fps ms apart).
            partial / path.name, writer=PillowWriter(fps=2 / step_s),  # type: ignore[arg-type]
            dpi=64)
        os.replace(partial / path.name, path)
    finally:
        plt.close(fig)
        shutil.rmtree(partial, ignore_errors=True)
    return path
