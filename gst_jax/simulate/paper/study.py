"""Every model on every scenario: measures, one PNG (and GIF) per run, results.json; and every
model on the same random encounters: rates with intervals, encounters.json and .png."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Mapping, Sequence

import jax
import numpy as np

from gst_jax.config import EVAL_TAU, TimeGrid
from gst_jax.errors import RunError
from gst_jax.model import Controls
from gst_jax.progress import Progress
from gst_jax.runs import Run
from gst_jax.simulate.agents.predicted import StepModel, constant_velocity_model, gst_model
from gst_jax.simulate.paper.encounters import (
    episode_measures,
    run_encounters,
    sample_encounters,
    summarize,
)
from gst_jax.simulate.paper.figures import animate_run, encounter_rates, plot_run
from gst_jax.simulate.paper.loop import MODEL_HUMANS, simulate
from gst_jax.simulate.paper.measures import robot_measures
from gst_jax.simulate.paper.scenarios import SCENARIOS

COLUMNS = ["scenario", "model", "min_distance_m", "collision_steps", "progress",
           "path_length_ratio", "u_turn", "frozen"]


def step_models(runs: Sequence[Run], edge_heads: Sequence[int] | None = None
                ) -> list[tuple[str, StepModel]]:
    """Constant velocity, then every run at each n of `edge_heads` (default: its own n)."""
    models: list[tuple[str, StepModel]] = [("constant velocity", constant_velocity_model)]
    for run in runs:
        label = Path(run.name).name        # 'eth-paper-...', 'hotel:n4-...', 'pretrained:eth'
        config = run.model_config
        if edge_heads and not config.selects_edges:
            # Built for full connection alone, its program has no selector: give it one.
            config = dataclasses.replace(config, max_edge_heads=config.head_slots)
        for n in edge_heads or [config.num_edge_heads]:
            controls = Controls.make(EVAL_TAU, n, config.ghost)
            models.append((f"{label} n={n if n else 'F'}", gst_model(run.params, config,
                                                                     controls)))
    return models


def time_grid(runs: Sequence[Run]) -> TimeGrid:
    """The time grid the runs share (the paper's without a run): the simulator's steps."""
    grids = {run.model_config.grid for run in runs} or {TimeGrid()}
    if len(grids) > 1:
        raise RunError("the models have different time grids ("
                       + ", ".join(f"{g.step_s:g} s, {g.obs_len} observed" for g in grids)
                       + "): simulate them separately")
    return grids.pop()


def run_scenarios(models: Sequence[tuple[str, StepModel]], scenario_names: Sequence[str],
                  out: Path, *, grid: TimeGrid = TimeGrid(), seed: int = 0,
                  animate: bool = False, humans: str = MODEL_HUMANS) -> list[dict]:
    """Simulate every model in every scenario on the models' time grid, the people moved as
    `humans` says; one row of measures (and figure paths) each. Writes out/results.json and
    the figures."""
    rows = []
    for name in scenario_names:
        scenario = SCENARIOS[name](grid)
        for label, model in models:
            positions = np.asarray(simulate(model, scenario, jax.random.key(seed), humans))
            row = {"scenario": scenario.name, "model": label,
                   **robot_measures(positions, scenario)}
            stem = f"{scenario.name}-{label.replace(' ', '_').replace('=', '').replace(':', '_')}"
            title = f"{scenario.name}, {label}"
            row["figure"] = str(plot_run(positions, scenario, out / f"{stem}.png", title))
            if animate:
                row["animation"] = str(animate_run(positions, scenario, out / f"{stem}.gif",
                                                   title))
            rows.append(row)
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(rows, indent=2) + "\n")
    return rows


def format_markdown(rows: Sequence[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        lines.append("| " + " | ".join(f"{row[c]:.2f}" if isinstance(row[c], float)
                                       else str(row[c]) for c in COLUMNS) + " |")
    return "\n".join(lines)


def run_encounter_study(models: Sequence[tuple[str, StepModel]], count: int, out: Path, *,
                        grid: TimeGrid = TimeGrid(), seed: int = 0,
                        progress: Progress | None = None,
                        stored: Mapping[str, Path] | None = None,
                        humans: str = MODEL_HUMANS) -> tuple[dict, dict]:
    """Every model on the same `count` random encounters (`encounters.sample_encounters` of
    `seed`), one program each. Returns (summary per label, with compile and run seconds and
    episodes per second; per label the episodes' measures) and writes out/encounters.json
    and out/encounters.png.

    stored: per label, a file that keeps the model's measures of these encounters: read when
    it holds the same episodes (count, seed, time step), else simulated and written, so that a
    study that grows simulates only its new members (an n = 16 model runs 2 episodes / s).
    """
    episodes = sample_encounters(count, seed, grid)
    progress = progress or Progress()
    stored = stored or {}
    same_episodes = {"episodes": count, "seed": seed, "step_s": grid.step_s,
                     # records of the model's people (the paper's) name none
                     **({} if humans == MODEL_HUMANS else {"humans": humans})}
    summaries, rows = {}, {}
    for label, model in models:
        path = stored.get(label)
        kept = json.loads(path.read_text()) if path and path.is_file() else {}
        if {key: kept.get(key) for key in same_episodes} == same_episodes:
            summaries[label], rows[label] = kept["summary"], kept["rows"]
            progress.line(f"{label}: {count} episodes read from {path}")
            continue
        positions, compile_s, run_s = run_encounters(model, episodes, jax.random.key(seed),
                                                      humans)
        rows[label] = episode_measures(positions, episodes)
        summaries[label] = {**summarize(rows[label]), "compile_s": compile_s, "run_s": run_s,
                            "episodes_per_s": count / run_s}
        progress.line(f"{label}: {count} episodes in {run_s:.1f} s ({count / run_s:.1f}/s) "
                      f"after {compile_s:.1f} s compiling")
        if path:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps({**same_episodes, "summary": summaries[label],
                                        "rows": rows[label]}) + "\n")
    out.mkdir(parents=True, exist_ok=True)
    (out / "encounters.json").write_text(json.dumps(
        {"episodes": count, "seed": seed, "step_s": grid.step_s, "models": summaries},
        indent=1) + "\n")
    draw_encounter_rates(summaries, count, seed, out)
    return summaries, rows


def draw_encounter_rates(summaries: Mapping[str, dict], count: int, seed: int, out: Path) -> Path:
    """out/encounters.png: per model, its rates of freezing and of collisions."""
    return encounter_rates(dict(summaries), out / "encounters.png",
                           f"{count} random encounters (seed {seed}), 95% intervals")
