"""Closed-loop multi-agent simulation driven by a trajectory predictor (the paper's Fig. 5).

    python -m gst_jax.simulate runs/eth-paper-d-n1-e200-seed1000 --scenario all

Holonomic agents on a plane, 0.4 s steps. Agent 0 is the robot; it is an agent like the
others. At every step each detected agent moves by the first displacement a model predicts
from the last 8 observed steps of everyone detected. An agent not yet detected walks its
scripted straight line, unseen by the model, until its detection step. The whole loop is one
jitted `lax.scan` with the model call inside.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.data.batch import SceneBatch
from gst_jax.model import Controls
from gst_jax.rollout import rollout

DT = 0.4
OBS_LEN = 8
COLLISION_DISTANCE = 0.3


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Initial state of A agents (agent 0 = robot); all arrays numpy.

    start (A, 2) position at step 0; velocity (A, 2) m/s of the scripted straight line (also
    the 8-step history before step 0); detected_from (A,) step from which an agent is seen
    (0 = from the start, history included); goal (2,) the robot's goal.
    """

    name: str
    start: np.ndarray
    velocity: np.ndarray
    detected_from: np.ndarray
    goal: np.ndarray
    steps: int = 25


def late_crossing(delay_s: float = 1.6, speed: float = 1.2) -> Scenario:
    """(a) A human enters the robot's field of view `delay_s` late, walking into its path."""
    start = np.array([[0.0, 0.0], [6.0, -6.0]])       # both reach (6, 0) after 5 s
    velocity = np.array([[speed, 0.0], [0.0, speed]])
    return Scenario("a_late_crossing", start, velocity,
                    np.array([0, round(delay_s / DT)]), np.array([12.0, 0.0]))


def boundary_wanderers(num_wanderers: int = 6, speed: float = 1.2, seed: int = 0) -> Scenario:
    """(b) Six humans wander near the boundary while one walks straight at the robot."""
    rng = np.random.default_rng(seed)
    angles = np.linspace(0, 2 * np.pi, num_wanderers, endpoint=False)
    ring = 6.0 + np.stack([7 * np.cos(angles), 7 * np.sin(angles)], -1)
    tangent = 0.5 * np.stack([-np.sin(angles), np.cos(angles)], -1) + rng.normal(0, 0.05, (num_wanderers, 2))
    start = np.concatenate([[[0.0, 0.0], [12.0, 0.0]], ring])
    velocity = np.concatenate([[[speed, 0.0], [-speed, 0.0]], tangent])
    return Scenario("b_boundary_wanderers", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]))


def intersection(num_humans: int = 3, speed: float = 1.2) -> Scenario:
    """(c) The robot and a file of humans meet at an intersection."""
    humans = np.stack([np.full(num_humans, 6.0), -6.0 - 1.2 * np.arange(num_humans)], -1)
    start = np.concatenate([[[0.0, 0.0]], humans])
    velocity = np.concatenate([[[speed, 0.0]], np.tile([[0.0, speed]], (num_humans, 1))])
    return Scenario("c_intersection", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]))


def oncoming_group(group_size: int = 8, speed: float = 1.2) -> Scenario:
    """(d) The robot moving right meets a group of eight humans moving left."""
    rows, cols = 2, (group_size + 1) // 2
    group = np.array([[12.0 + 0.8 * c, -0.6 + 1.2 * r] for r in range(rows)
                      for c in range(cols)])[:group_size]
    start = np.concatenate([[[0.0, 0.0]], group])
    velocity = np.concatenate([[[speed, 0.0]], np.tile([[-speed, 0.0]], (group_size, 1))])
    return Scenario("d_oncoming_group", start, velocity, np.zeros(len(start), int),
                    np.array([12.0, 0.0]))


SCENARIOS: dict[str, Callable[[], Scenario]] = {
    "a": late_crossing, "b": boundary_wanderers, "c": intersection, "d": oncoming_group}

# A model: (positions (T_obs, A, 2), mask (T_obs, A), key) -> next displacement (A, 2).
StepModel = Callable[[jax.Array, jax.Array, jax.Array], jax.Array]


def constant_velocity_model(positions: jax.Array, mask: jax.Array, key: jax.Array) -> jax.Array:
    """Repeat each agent's last observed displacement (zero without two observations)."""
    both = mask[-1] * mask[-2]
    return (positions[-1] - positions[-2]) * both[:, None]


def gst_model(params, config, controls: Controls) -> StepModel:
    """The first predicted displacement of a GST (hard samples, no dropout)."""
    if config.temporal == "lstm":
        # The first displacement comes from the observed state, before any predicted step;
        # the TCN readout's layers are sized by pred_len, so it keeps them.
        config = dataclasses.replace(config, pred_len=1)

    def step(positions, mask, key):
        pad = config.pred_len
        positions = jnp.concatenate([positions, jnp.zeros((pad,) + positions.shape[1:])])
        mask = jnp.concatenate([mask, jnp.zeros((pad,) + mask.shape[1:])])
        node_mask = jnp.concatenate([mask[:1], mask[1:] * mask[:-1]])   # MODEL.md 1.6
        batch = SceneBatch(positions=positions[None] * mask[None, ..., None],
                           position_mask=mask[None], node_mask=node_mask[None],
                           scene_mask=jnp.ones(1), window_index=jnp.zeros(1, jnp.int32))
        out = rollout(params, config, batch, key, controls, hard=True, deterministic=True)
        return out.displacements[0, 0]

    return step


def simulate(model: StepModel, scenario: Scenario, key: jax.Array) -> jax.Array:
    """Positions (steps + 1, A, 2) of every agent, step 0 first. Jit-compiled closed loop."""
    start = jnp.asarray(scenario.start, jnp.float32)
    velocity = jnp.asarray(scenario.velocity, jnp.float32)
    # Agents seen from step 0 are also seen during their 8-step history before it.
    detected_from = jnp.asarray(scenario.detected_from)
    first_seen = jnp.where(detected_from == 0, -OBS_LEN, detected_from)
    history = start[None] + velocity[None] * DT * jnp.arange(-OBS_LEN + 1, 1)[:, None, None]

    @jax.jit
    def run(key):
        def step(carry, t):
            history, key = carry
            key, model_key = jax.random.split(key)
            # Steps t-7..t: seen where the agent was already detected at that step.
            seen = ((t - OBS_LEN + 1 + jnp.arange(OBS_LEN))[:, None] >= first_seen[None])
            seen = seen.astype(jnp.float32)
            predicted = model(history, seen, model_key)
            detected_now = (t >= detected_from)[:, None]
            move = jnp.where(detected_now, predicted, velocity * DT)
            position = history[-1] + move
            return (jnp.concatenate([history[1:], position[None]]), key), position

        _, positions = jax.lax.scan(step, (history, key), jnp.arange(scenario.steps))
        return jnp.concatenate([start[None], positions])

    return run(key)


def measures(positions: np.ndarray, scenario: Scenario) -> dict:
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
        "collision_steps": int(np.sum(distances.min(axis=1) < COLLISION_DISTANCE))
        if distances.size else 0,
        "progress": float((to_goal[0] - to_goal[arrival]) / to_goal[0]),
        "path_length_ratio": path_length / straight if straight > 1e-6 else float("inf"),
        **freezing_or_u_turn(robot[:arrival + 1], goal),
    }


def freezing_or_u_turn(robot: np.ndarray, goal: np.ndarray, *, reverse_deg: float = 120.0,
                       stall_s: float = 2.0, stall_speed: float = 0.1) -> dict:
    """U-turn: the robot's heading turns by more than `reverse_deg` from its initial heading.
    Freezing: progress toward the goal below `stall_speed` m/s for more than `stall_s`."""
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
    progress_speed = np.sum(steps * direction, axis=-1) / DT
    stalled = progress_speed < stall_speed
    longest, run = 0, 0
    for s in stalled:
        run = run + 1 if s else 0
        longest = max(longest, run)
    frozen = longest * DT > stall_s
    return {"u_turn": u_turn, "frozen": bool(frozen), "freezing_or_u_turn": u_turn or bool(frozen)}


def plot_run(positions: np.ndarray, scenario: Scenario, path: Path, title: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def animate_run(positions: np.ndarray, scenario: Scenario, path: Path, title: str,
                fps: float = 2 / DT) -> Path:
    """Animated GIF of a run (Pillow writer), one frame per step at `fps` (default 2x real
    time): trails so far, agents as dots, undetected agents hollow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.animation import FuncAnimation, PillowWriter

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
        path, writer=PillowWriter(fps=fps), dpi=80)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    import argparse

    from gst_jax.evaluate import load_run
    from gst_jax.pretrained import load_pretrained
    from gst_jax.sweep import load_member

    parser = argparse.ArgumentParser(prog="python -m gst_jax.simulate",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="*", help="work directories of trained models, or "
                        "SWEEP_DIR:MEMBER for one member of a sweep (e.g. "
                        "runs/sweep-hotel-e10:n4-partial-seed1000), or pretrained:NAME for a "
                        "shipped model (e.g. pretrained:eth); none = only the "
                        "constant-velocity model")
    parser.add_argument("--scenario", default="all", choices=("all", *SCENARIOS),
                        help="a: late crossing, b: boundary wanderers, c: intersection, "
                             "d: oncoming group (default: all)")
    parser.add_argument("--edge-heads", default=None,
                        help="comma-separated n to run each model with (traced; default: the "
                             "model's own)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Gumbel samples")
    parser.add_argument("--animate", action="store_true",
                        help="also write an animated GIF of every run")
    parser.add_argument("--workdir", default="runs/simulate", help="output directory")
    parser.add_argument("--json", action="store_true", help="print the table as JSON")
    args = parser.parse_args(argv)

    models: list[tuple[str, StepModel]] = [("constant velocity", constant_velocity_model)]
    for run_path in args.runs:
        where, _, member = run_path.partition(":")
        if where == "pretrained":
            config, params = load_pretrained(member)
        else:
            run = load_member(where, member) if member else load_run(run_path)
            config, params = run.model_config, run.params
        heads = ([int(n) for n in args.edge_heads.split(",")] if args.edge_heads
                 else [config.num_edge_heads])
        for n in heads:
            controls = Controls.make(0.03, n, config.ghost)
            label = f"{Path(where).name}{':' + member if member else ''} n={n if n else 'F'}"
            models.append((label, gst_model(params, config, controls)))
    names = list(SCENARIOS) if args.scenario == "all" else [args.scenario]
    out = Path(args.workdir)
    rows = []
    for name in names:
        scenario = SCENARIOS[name]()
        for label, model in models:
            positions = np.asarray(simulate(model, scenario, jax.random.key(args.seed)))
            row = {"scenario": scenario.name, "model": label, **measures(positions, scenario)}
            stem = f"{scenario.name}-{label.replace(' ', '_').replace('=', '').replace(':', '_')}"
            row["figure"] = str(plot_run(positions, scenario, out / f"{stem}.png",
                                         f"{scenario.name}, {label}"))
            if args.animate:
                row["animation"] = str(animate_run(positions, scenario, out / f"{stem}.gif",
                                                   f"{scenario.name}, {label}"))
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    columns = ["scenario", "model", "min_distance_m", "collision_steps", "progress",
               "path_length_ratio", "u_turn", "frozen"]
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in rows:
        print("| " + " | ".join(f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c])
                                for c in columns) + " |")
    figures = "PNG and GIF" if args.animate else "PNG"
    print(f"written: {out}/results.json and one {figures} per run", file=sys.stderr)


if __name__ == "__main__":
    main()
