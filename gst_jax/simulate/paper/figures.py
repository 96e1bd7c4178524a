"""A simulated run as a PNG of the paths and as an animated GIF (matplotlib, Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.animation import FuncAnimation, PillowWriter

from gst_jax.figures import plt, save
from gst_jax.simulate.paper.scenarios import Scenario


def plot_run(positions: np.ndarray, scenario: Scenario, path: Path, title: str) -> Path:
    """PNG of every agent's path (dotted while not yet detected), the robot in red."""
    fig, ax = plt.subplots(figsize=(5.0, 4.0))
    for a in range(positions.shape[1]):
        seen = np.arange(positions.shape[0]) >= scenario.detected_from[a]
        color = "tab:red" if a == 0 else "tab:blue"
        ax.plot(positions[:, a, 0], positions[:, a, 1], ":", color=color, lw=0.8)
        ax.plot(positions[seen, a, 0], positions[seen, a, 1], "-", color=color, lw=1.5,
                label=("robot" if a == 0 else "human") if a < 2 else None)
        ax.plot(*positions[0, a], "o", color=color, ms=4)
    ax.plot(*scenario.goal, "*", color="tab:red", ms=10, label="robot goal")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return save(fig, path, dpi=120)


def animate_run(positions: np.ndarray, scenario: Scenario, path: Path, title: str,
                fps: float | None = None) -> Path:
    """Animated GIF of a run (Pillow writer), one frame per step at `fps` (default 2x real
    time): trails so far, agents as dots, undetected agents hollow."""
    fps = fps or 2 / scenario.grid.step_s
    num_steps, num_agents = positions.shape[:2]
    colors = ["tab:red"] + ["tab:blue"] * (num_agents - 1)
    lo, hi = positions.reshape(-1, 2).min(0) - 0.5, positions.reshape(-1, 2).max(0) + 0.5
    aspect = (hi[1] - lo[1]) / (hi[0] - lo[0])
    fig, ax = plt.subplots(figsize=(4.0, float(np.clip(4.0 * aspect, 1.5, 4.0)) + 0.5))
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.plot(*scenario.goal, "*", color="tab:red", ms=9)
    ax.set_title(title, fontsize=7)
    ax.tick_params(labelsize=6)
    trails = [ax.plot([], [], "-", color=c, lw=1.2)[0] for c in colors]
    dots = [ax.plot([], [], "o", color=c, ms=5)[0] for c in colors]

    def draw(t: int) -> list:
        for a in range(num_agents):
            trails[a].set_data(positions[:t + 1, a, 0], positions[:t + 1, a, 1])
            dots[a].set_data(positions[t, a, :1], positions[t, a, 1:])
            dots[a].set_markerfacecolor(colors[a] if t >= scenario.detected_from[a] else "none")
        return trails + dots

    path.parent.mkdir(parents=True, exist_ok=True)
    FuncAnimation(fig, draw, frames=num_steps, blit=True).save(
        # matplotlib's stubs want an int; a GIF takes any rate (frames 1000 / fps ms apart).
        path, writer=PillowWriter(fps=fps), dpi=80)  # type: ignore[arg-type]
    plt.close(fig)
    return path


def encounter_rates(summaries: dict[str, dict], path: Path, title: str) -> Path:
    """PNG: per model, the rates of freezing or turning back and of collisions over the
    random encounters, with their 95 % intervals."""
    labels = list(summaries)
    fig, ax = plt.subplots(figsize=(max(4.0, 0.9 * len(labels) + 1.5), 3.4))
    x = np.arange(len(labels))
    for offset, (key, name, color) in zip((-0.2, 0.2), [
            ("freezing_or_u_turn", "froze or turned back", "tab:red"),
            ("collided", "collided", "tab:blue")]):
        value, low, high = np.array([summaries[label][key] for label in labels]).T
        ax.bar(x + offset, value, 0.4, color=color, label=name,
               yerr=[value - low, high - value], capsize=3)
    ax.set_xticks(x, labels, rotation=30, ha="right", fontsize=7)
    ax.set_ylabel("fraction of episodes")
    ax.set_ylim(0, 1)
    ax.legend(fontsize=7)
    ax.set_title(title, fontsize=8)
    return save(fig, path, dpi=120)
