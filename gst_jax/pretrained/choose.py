"""Which shipped model for your data? Every shipped model whose time grid reads the data, and
constant velocity, scored on the data's validation windows and ranked by AOE:

    python -m gst_jax.pretrained choose --data plaza.csv --fps 10 --units cm

The windows are the validation split of protocol `paper-val`, the windows a fine-tuning
(`train --init`) keeps its epoch on; the test split is never read, so it stays a fair test of
the model chosen. Each model predicts K samples of every window as `evaluate` does (hard
graphs, tau 0.03, the same seed for every model), so its AOE / FOE are `evaluate`'s on the
same windows. Intervals are 95 % percentile intervals of a bootstrap over windows (a window's
people, who walk together, resampled together), the same resamples for every row; "AOE - CV"
is the paired difference from constant velocity on those resamples.

Models on different time grids (step, observed and predicted steps) get a table each, with
constant velocity on that grid: a 4.8 s horizon's errors are not comparable with a 1.25 s
one's. A model whose grid cannot read the data (a time step the data's rate does not fit) is
listed as skipped, with the data layer's reason.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import shlex
from typing import Iterable, Sequence

import jax
import numpy as np

from gst_jax import data, paired, pretrained
from gst_jax.compiles import count_compiles
from gst_jax.config import DataConfig, ModelConfig, TimeGrid
from gst_jax.data.protocols import has_validation
from gst_jax.data.readers import UNITS
from gst_jax.errors import DataError
from gst_jax.evaluation import predict_windows
from gst_jax.model.weights import PRETRAINED
from gst_jax.predict import Predictor, make_predict
from gst_jax.progress import Progress, StepClock
from gst_jax.runs import load_model
from gst_jax.strata import pedestrian_records

SPLIT = "val"
CONSTANT_VELOCITY = "constant velocity"
# Epochs of the fine-tuning command printed for the best model: those of docs/own-data.md's
# measured fine-tunings ("When fine-tuning is worth it"); the epoch kept is chosen on the
# validation windows, the starting model included.
FINE_TUNE_EPOCHS = 20


@dataclasses.dataclass(frozen=True)
class Row:
    """One predictor on a table's windows: `pretrained:NAME` or constant velocity.

    aoe, foe: metres, over the windows' fully detected pedestrians (the mean over K samples);
    aoe_interval: its 95 % bootstrap interval over windows; minus_cv: AOE minus constant
    velocity's (negative: better), with its paired interval (0 for constant velocity)."""

    name: str
    aoe: float
    foe: float
    aoe_interval: tuple[float, float]
    minus_cv: float
    minus_cv_interval: tuple[float, float]


@dataclasses.dataclass(frozen=True)
class Table:
    """The models of one time grid and constant velocity, ranked by AOE (best first), on
    `windows` validation windows holding `pedestrians` fully detected pedestrians."""

    grid: TimeGrid
    windows: int
    pedestrians: int
    rows: tuple[Row, ...]

    @property
    def best_model(self) -> Row:
        """The best of the shipped models (constant velocity may rank above it)."""
        return next(row for row in self.rows if row.name != CONSTANT_VELOCITY)


@dataclasses.dataclass(frozen=True)
class Choice:
    """The ranking: one table per time grid, and the models skipped with their reasons."""

    data_config: DataConfig
    samples: int
    tables: tuple[Table, ...]
    skipped: tuple[tuple[str, str], ...]


def choose(data_config: DataConfig, models: Sequence[str] | None = None, *,
           num_samples: int = 20, seed: int = 0, progress: Progress | None = None) -> Choice:
    """Score `models` (shipped names; None: every shipped model) and constant velocity on the
    validation windows of `data_config` (a protocol with a validation split, `paper-val`),
    each grid's on its own windows. progress: a line per model scored, with an ETA. Refuses
    (DataError) data no model's grid reads."""
    if not has_validation(data_config):
        raise DataError(f"protocol {data_config.protocol!r} has no validation split to choose "
                        "a model on; use 'paper-val' (the test split stays untouched)")
    names = [pretrained.folder(name).name for name in
             (pretrained.available() if models is None else models)]
    by_grid: dict[TimeGrid, list[str]] = {}
    for name in dict.fromkeys(names):
        by_grid.setdefault(model_grid(name), []).append(name)
    window_sets, skipped, errors = {}, [], {}
    for grid, group in by_grid.items():
        try:
            window_sets[grid] = _validation_windows(data_config, grid)
        except DataError as error:
            errors[str(error)] = grid
            skipped += [(name, f"{grid_text(grid)}: {error}") for name in group]
    if not window_sets:            # the same error on every grid is the data's, not a grid's
        raise DataError(next(iter(errors)) if len(errors) == 1 else (
            f"no shipped model reads {data_config.scene}'s validation windows: "
            + "; ".join(f"{grid_text(grid)}: {error}" for error, grid in errors.items())))
    scored = _score(data_config, {grid: by_grid[grid] for grid in window_sets}, window_sets,
                    num_samples, seed, progress or Progress())
    return Choice(data_config, num_samples, scored, tuple(skipped))


def report(data_config: DataConfig, models: Sequence[str] | None = None, *,
           num_samples: int = 20, seed: int = 0, as_json: bool = False) -> str:
    """`choose`'s ranking as `python -m gst_jax.pretrained choose` prints it: its tables and
    advice (`format_choice`), or JSON."""
    choice = choose(data_config, models, num_samples=num_samples, seed=seed)
    return json.dumps(dataclasses.asdict(choice), indent=2) if as_json else format_choice(choice)


def model_grid(name: str) -> TimeGrid:
    """A shipped model's time grid, from its record (no weights loaded)."""
    return ModelConfig.from_dict(pretrained.load_meta(name)["model"]).grid


def grid_text(grid: TimeGrid) -> str:
    return (f"time step {grid.step_s:g} s, {grid.obs_len} observed + {grid.pred_len} "
            "predicted steps")


def _validation_windows(data_config: DataConfig, grid: TimeGrid) -> data.WindowSet:
    window_set = data.load_split(data_config, SPLIT, grid)
    if not len(window_set):
        raise DataError(data.no_windows_message(window_set, data_config, SPLIT, grid))
    return window_set


def _score(data_config: DataConfig, by_grid: dict[TimeGrid, list[str]],
           window_sets: dict[TimeGrid, data.WindowSet], num_samples: int, seed: int,
           progress: Progress) -> tuple[Table, ...]:
    """Each grid's table. Models of one architecture share one predict (`_predictor`: one
    compile per batch shape); the ETA leaves compiling out (`StepClock`)."""
    total, done = sum(len(group) for group in by_grid.values()), 0
    clock, tables = StepClock(), []
    with count_compiles() as compiles:
        for grid, group in by_grid.items():
            window_set = window_sets[grid]
            sums: dict[str, tuple[np.ndarray, np.ndarray]] = {}
            counts: np.ndarray = np.zeros(len(window_set), int)   # scored people per window
            for name in group:
                run = load_model(PRETRAINED + name)
                predict = _predictor(run.model_config, num_samples)
                records = pedestrian_records(predict_windows(
                    run.params, jax.random.key(seed), window_set, run.model_config,
                    num_samples=num_samples, predict=predict,
                    fully_detected_only=run.train_config.fully_detected_only), grid.obs_len)
                counts = np.bincount(records["window"], minlength=len(window_set))
                sums[run.name] = _window_sums(records, "model", len(window_set))
                sums.setdefault(CONSTANT_VELOCITY, _window_sums(records, "cv", len(window_set)))
                done += 1
                progress.line(f"models scored {done}/{total} ({name}), ETA "
                              f"{clock.eta(done, total - done, compiles.seconds)}")
            tables.append(ranked_table(grid, sums, counts))
    return tuple(tables)


@functools.lru_cache(maxsize=8)
def _predictor(config: ModelConfig, num_samples: int) -> Predictor:
    """One predict per architecture and K, shared by the models that have it and kept for
    the process's next choice (its programs compiled once)."""
    return make_predict(config, num_samples, with_graph=False)


def _window_sums(records: dict[str, np.ndarray], predictor: str, windows: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(ADE, FDE) of `predictor` summed over each window's scored pedestrians, (W,) each."""
    ade, fde = (np.bincount(records["window"], weights=records[f"{predictor}_{error}"],
                            minlength=windows) for error in ("ade", "fde"))
    return ade, fde


def ranked_table(grid: TimeGrid, sums: dict[str, tuple[np.ndarray, np.ndarray]],
                 counts: np.ndarray) -> Table:
    """The rows of `sums` (name -> ADE and FDE summed over each window's scored pedestrians,
    (W,) each; constant velocity among them) ranked by AOE, with `counts` (W,) the scored
    pedestrians of each window; intervals from a bootstrap over windows, every row on the
    same resamples (paired.BOOTSTRAP_RESAMPLES, paired.BOOTSTRAP_SEED)."""
    rng = np.random.default_rng(paired.BOOTSTRAP_SEED)
    draws = rng.integers(0, len(counts), (paired.BOOTSTRAP_RESAMPLES, len(counts)))
    times_drawn = np.zeros(draws.shape)                  # (R, W): how often each window
    np.add.at(times_drawn, (np.arange(len(draws))[:, None], draws), 1.0)
    resampled_counts = times_drawn @ counts
    cv_ade = sums[CONSTANT_VELOCITY][0]

    def interval(per_window: np.ndarray) -> tuple[float, float]:
        low, high = np.quantile(times_drawn @ per_window / resampled_counts, [0.025, 0.975])
        return float(low), float(high)

    rows = [Row(name, float(ade.sum() / counts.sum()), float(fde.sum() / counts.sum()),
                interval(ade), float((ade - cv_ade).sum() / counts.sum()),
                interval(ade - cv_ade))
            for name, (ade, fde) in sums.items()]
    rows.sort(key=lambda row: row.aoe)
    return Table(grid, len(counts), int(counts.sum()), tuple(rows))


def fine_tune_command(data_config: DataConfig, model: str) -> str:
    """`python3 -m gst_jax.train` fine-tuning `model` on the data of `data_config` (its
    validation split is the one the model was chosen on)."""
    if data_config.data:
        flags = ["--data", _shown(data_config.data)]
        flags += ["--fps", f"{data_config.fps:g}"] if data_config.fps else []
        unit = next((u for u, scale in UNITS.items() if scale == data_config.scale), None)
        flags += ["--units", unit] if unit not in (None, "m") else []
        flags += ["--columns", data_config.columns] if data_config.columns else []
    else:
        flags = ["--scene", data_config.scene]
    flags += ["--drop-off-grid"] if data_config.drop_off_grid else []
    flags += ["--data-dir", _shown(data_config.data_dir)] if data_config.data_dir else []
    name = model.removeprefix(PRETRAINED)
    return shlex.join(["python3", "-m", "gst_jax.train", *flags, "--init", model, "--epochs",
                       str(FINE_TUNE_EPOCHS), "--workdir",
                       f"runs/{data_config.scene}-{name}-tuned"])


def _shown(path: str) -> str:
    """A path inside the working directory as a relative one (shorter to read and copy)."""
    relative = os.path.relpath(path) if os.path.isabs(path) else path
    return relative if not relative.startswith("..") else path


def format_choice(choice: Choice) -> str:
    """The ranked tables, the models skipped and why, and the command that fine-tunes the
    best model."""
    config = choice.data_config
    lines = [f"{config.scene}: validation windows ({config.protocol} protocol; the test split "
             f"is not read), {choice.samples} samples of each; AOE / FOE in metres, ranked by "
             "AOE"]
    for table in choice.tables:
        lines += ["", f"{grid_text(table.grid)}: {table.windows} windows, {table.pedestrians} "
                  "fully detected pedestrians", *_table_lines(table)]
    lines += ["", "95 % intervals: percentile bootstrap over the windows "
              f"({paired.BOOTSTRAP_RESAMPLES:,} resamples, the same for every row; AOE - CV "
              "paired)."]
    for reason, names in _grouped(choice.skipped).items():
        lines.append(f"skipped {', '.join(names)}: {reason}")
    if not config.data:
        lines.append(f"note: {config.scene}'s validation windows lie in its paper train split, "
                     "which crowd_d, crowd_p and the scene's own models (if any) trained on: "
                     "they rank higher here than they would on new data")
    for table in choice.tables:
        lines += ["", *_advice(config, table)]
    return "\n".join(lines)


def _table_lines(table: Table) -> list[str]:
    header = ("rank", "model", "AOE", "95 % interval", "FOE", "AOE - CV", "95 % interval")
    cells = [header] + [
        (str(rank), row.name, f"{row.aoe:.3f}", _interval(row.aoe_interval, "{:.3f}"),
         f"{row.foe:.3f}", "-" if row.name == CONSTANT_VELOCITY else f"{row.minus_cv:+.3f}",
         "-" if row.name == CONSTANT_VELOCITY else _interval(row.minus_cv_interval, "{:+.3f}"))
        for rank, row in enumerate(table.rows, 1)]
    widths = [max(len(row[i]) for row in cells) for i in range(len(header))]
    return ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip()
            for row in cells]


def _interval(bounds: tuple[float, float], number: str) -> str:
    return f"{number.format(bounds[0])} to {number.format(bounds[1])}"


def _grouped(skipped: Iterable[tuple[str, str]]) -> dict[str, list[str]]:
    grouped: dict[str, list[str]] = {}
    for name, reason in skipped:
        grouped.setdefault(reason, []).append(name)
    return grouped


def _advice(config: DataConfig, table: Table) -> list[str]:
    """Which model to start from, and the command that fine-tunes it."""
    best = table.best_model
    command = "  " + fine_tune_command(config, best.name)
    difference = (f"AOE - CV {best.minus_cv:+.3f} m, 95 % "
                  f"{_interval(best.minus_cv_interval, '{:+.3f}')}")
    if table.rows[0].name == CONSTANT_VELOCITY:
        return [f"Constant velocity beats every shipped model on these windows; the best "
                f"model, {best.name} ({difference}), is where a fine-tuning would start; in "
                "docs/own-data.md's measurements fine-tuning did not close such a gap:", command]
    if best.minus_cv_interval[1] >= 0:       # ahead, but these windows cannot tell them apart
        return [f"{best.name} leads constant velocity on these windows, but not beyond the "
                f"95 % interval ({difference}): more windows would tell them apart. To "
                "fine-tune it on your data (the epoch kept is chosen on these windows):", command]
    return [f"Start from {best.name} ({difference}); to fine-tune it on your data (the epoch "
            "kept is chosen on these validation windows):", command]
