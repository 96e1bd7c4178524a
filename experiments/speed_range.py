"""The walking speeds each shipped model predicts sensibly (issue 92, item 7):

    python experiments/speed_range.py                  # runs/speed_range/speed_range.{md,json}
    python experiments/speed_range.py --publish        # results/speed_range.{md,json}
    python experiments/speed_range.py --models crowdnav_sj eth_d

Straight-line walkers at 0.25, 0.5, ..., 6 m/s, on each model's own time grid (its step,
observed and predicted steps), fully detected at every observed step, in 8 directions (every
45 degrees): alone, and as a row of 3 walking abreast 0.8 m apart at the same speed, in
slots padded to their size bucket with undetected ones, as `make_batch` and `Stream` hand
them to a model. That matters for `crowdnav_sj`: its release attention (a softmax over
every slot, then masked) underflows for a lone walker once any undetected slot is beside it,
so in a slot of its own (or with `attention="masked"`, in any slots) it predicts that walker
otherwise; for crowdnav_sim, eth_d and eth_p padding changed nothing beyond 1e-6. Each model
predicts in mean mode (one run of each step's mean; GST (P)'s Gaussian mean, the edges
still sampled at tau 0.03 with one fixed key), and each walker's prediction is scored against
the straight continuation of its walk:

- FDE share: the final displacement error over the distance walked in the horizon
  (speed x pred_len x step);
- heading error: the angle between the walking direction and the last predicted step's
  displacement (where the prediction has the walker heading at the horizon's end);
- speed ratio: the predicted progress along the walking direction at the horizon's end
  over the distance walked (1: the right speed; below 0 backwards).

The rule: a speed is predicted sensibly where, in every direction, alone and for each walker
of the row, the FDE share is at most 25 % and the heading error at most 30 degrees. A model's
speed range is the longest run of consecutive grid speeds (0.25 m/s apart) that pass, the
slower run on a tie; speeds passing outside it are listed beside it. Constant velocity is
measured on the same walkers as the baseline: on a straight line at constant speed it is
exact (zero error at every speed), trivially, so it is the yardstick, not a competitor.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from _common import add_results_flags, results_folder
from gst_jax import pretrained
from gst_jax.config import TimeGrid
from gst_jax.data import bucket_size
from gst_jax.predictors import GST, ConstantVelocity, Predictor
from gst_jax.progress import Progress

SPEEDS = tuple(0.25 * k for k in range(1, 25))              # m/s, 0.25 to 6
HEADINGS_DEG = tuple(range(0, 360, 45))
ROW_SIZE, ROW_SPACING_M = 3, 0.8                            # walkers abreast, metres apart
MAX_FDE_SHARE = 0.25
MAX_HEADING_ERROR_DEG = 30.0
CASES = {"alone": 1, "row of 3": ROW_SIZE}


def straight_walkers(speeds, grid: TimeGrid, walkers: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Walkers abreast at each speed in each of HEADINGS_DEG, S = speeds x headings scenes.

    Returns histories (S, C, obs_len, 2) (the middle walker's last observed position at the
    origin), their straight continuations (S, C, pred_len, 2) and the walking directions
    (S, 2), speeds varying slowest."""
    angles = np.deg2rad(np.asarray(HEADINGS_DEG, dtype=np.float64))
    direction = np.tile(np.stack([np.cos(angles), np.sin(angles)], -1), (len(speeds), 1))
    speed = np.repeat(np.asarray(speeds, dtype=np.float64), len(angles))
    lateral = (np.arange(walkers) - (walkers - 1) / 2) * ROW_SPACING_M           # (C,)
    side = np.stack([-direction[:, 1], direction[:, 0]], -1)                     # (S, 2)
    start = lateral[None, :, None] * side[:, None, :]                            # (S, C, 2)
    times = np.arange(-grid.obs_len + 1, grid.pred_len + 1) * grid.step_s       # (T,)
    path = (start[:, :, None] + (speed[:, None] * times)[:, None, :, None]
            * direction[:, None, None, :])                                       # (S, C, T, 2)
    return path[:, :, :grid.obs_len], path[:, :, grid.obs_len:], direction


def errors(predicted: np.ndarray, truth: np.ndarray, last_observed: np.ndarray,
           direction: np.ndarray) -> dict[str, np.ndarray]:
    """Each walker's scores, (S, C) each: `fde_share`, `heading_error_deg`, `speed_ratio`
    (module docstring), from its predicted and true futures (S, C, P, 2), its last observed
    position (S, C, 2) and the walking direction (S, 2)."""
    walked = np.linalg.norm(truth[:, :, -1] - last_observed, axis=-1)
    fde = np.linalg.norm(predicted[:, :, -1] - truth[:, :, -1], axis=-1)
    before_last = np.concatenate([last_observed[:, :, None], predicted], axis=2)[:, :, -2]
    last_step = predicted[:, :, -1] - before_last
    cosine = (np.einsum("scx,sx->sc", last_step, direction)
              / np.maximum(np.linalg.norm(last_step, axis=-1), 1e-12))
    progress = np.einsum("scx,sx->sc", predicted[:, :, -1] - last_observed, direction)
    return {"fde_share": fde / walked,
            "heading_error_deg": np.rad2deg(np.arccos(np.clip(cosine, -1.0, 1.0))),
            "speed_ratio": progress / walked}


def within(scores: dict[str, np.ndarray]) -> np.ndarray:
    """Whether each walker's prediction passes the rule (module docstring)."""
    return ((scores["fde_share"] <= MAX_FDE_SHARE)
            & (scores["heading_error_deg"] <= MAX_HEADING_ERROR_DEG))


def speed_range(speeds, passed) -> dict:
    """The longest run of consecutive passing speeds (the slower on a tie) as
    {"low", "high"} (None where no speed passes), and `also`: the passing speeds outside it."""
    best: tuple[int, int] | None = None
    start = None
    for i, ok in enumerate([*passed, False]):
        if ok and start is None:
            start = i
        elif not ok and start is not None:
            if best is None or i - start > best[1] - best[0] + 1:
                best = (start, i - 1)
            start = None
    inside = set(range(best[0], best[1] + 1)) if best else set()
    return {"low": speeds[best[0]] if best else None, "high": speeds[best[1]] if best else None,
            "also": [s for i, (s, ok) in enumerate(zip(speeds, passed)) if ok and i not in inside]}


def predict_all(predictor: Predictor, params) -> Callable:
    """histories (S, C, T, 2) -> futures (S, C, P, 2): the predictor's first (mean) future of
    every scene, the C walkers in slots padded with undetected ones to C's size bucket (as
    `make_batch` and `Stream` hand them to a model); one jitted program per shape, one fixed
    key."""
    key = jax.random.key(0)

    @jax.jit
    def program(histories):
        walkers = histories.shape[1]
        padding = [(0, 0), (0, bucket_size(walkers) - walkers), (0, 0)]
        detected = jnp.pad(jnp.ones(histories.shape[:-1]), padding)
        slots = jnp.pad(histories, [*padding, (0, 0)])
        futures, _ = jax.vmap(lambda h, d: predictor.predict(params, key, h, d))(
            slots, detected)                                         # (S, K, P, C', 2)
        return jnp.moveaxis(futures[:, 0, :, :walkers], 1, 2)
    return program


def measure(predictor: Predictor, params, grid: TimeGrid, speeds=SPEEDS,
            cases: dict[str, int] = CASES) -> dict:
    """Per case (name: walkers abreast; default alone and the row of 3) and speed, over the
    headings and walkers: the largest FDE share and heading error, the smallest and largest
    speed ratio, and whether all passed; then each case's range and the range of the speeds
    passing in every case."""
    program = predict_all(predictor, params)
    out: dict = {"speeds": list(speeds), "cases": {}}
    passed_everywhere = np.ones(len(speeds), bool)
    for case, walkers in cases.items():
        histories, truth, direction = straight_walkers(speeds, grid, walkers)
        predicted = np.asarray(program(jnp.asarray(histories, jnp.float32)), np.float64)
        scores = errors(predicted, truth, histories[:, :, -1], direction)
        per_speed = {k: v.reshape(len(speeds), -1) for k, v in scores.items()}
        passed = within(scores).reshape(len(speeds), -1).all(axis=1)
        passed_everywhere &= passed
        out["cases"][case] = {
            "worst_fde_share": per_speed["fde_share"].max(axis=1).round(4).tolist(),
            "worst_heading_error_deg": per_speed["heading_error_deg"].max(axis=1).round(2)
                                                                     .tolist(),
            "speed_ratio_min": per_speed["speed_ratio"].min(axis=1).round(4).tolist(),
            "speed_ratio_max": per_speed["speed_ratio"].max(axis=1).round(4).tolist(),
            "passed": passed.tolist(), "range": speed_range(list(speeds), passed.tolist())}
    out["range"] = speed_range(list(speeds), passed_everywhere.tolist())
    return out


def measure_model(name: str, speeds=SPEEDS) -> dict:
    """A shipped model's measurement (`measure`) with its grid."""
    config, params = pretrained.load_pretrained(name)
    grid = config.grid
    return {"step_s": grid.step_s, "obs_len": grid.obs_len, "pred_len": grid.pred_len,
            **measure(GST(config, num_samples=1, mean=True), params, grid, speeds)}


def range_text(r: dict) -> str:
    if r["low"] is None:
        return "none"
    text = f"{r['low']:g}" + (f"-{r['high']:g}" if r["high"] != r["low"] else "")
    return text + (f" (also {', '.join(f'{s:g}' for s in r['also'])})" if r["also"] else "")


def markdown(rows: dict, command: str, seconds: float, machine: str) -> str:
    lines = ["# The walking speeds each shipped model predicts sensibly", "",
             f"Straight-line walkers at {SPEEDS[0]:g} to {SPEEDS[-1]:g} m/s (every "
             f"{SPEEDS[1] - SPEEDS[0]:g} m/s), on each model's own grid, fully detected, in "
             f"{len(HEADINGS_DEG)} directions, alone and as a row of {ROW_SIZE} abreast "
             f"{ROW_SPACING_M:g} m apart; mean-mode predictions scored against the straight "
             f"continuation. A speed passes where, in every direction and for every walker, "
             f"the final displacement error is at most {MAX_FDE_SHARE:.0%} of the distance "
             f"walked over the horizon and the last predicted step heads within "
             f"{MAX_HEADING_ERROR_DEG:g} degrees of the walk; the range is the longest run of "
             "consecutive passing speeds (m/s). Constant velocity is exact on these walkers "
             "(zero error at every speed, trivially: a straight line at constant speed is its "
             "own assumption), measured as the baseline. The speed ratio is the predicted "
             "progress along the walk over the distance walked (1 is right, below 0 "
             "backwards), its range over directions and walkers. The walkers sit in slots "
             "padded to their size bucket with undetected ones, as `make_batch` and `Stream` "
             "hand them to a model (crowdnav_sj predicts a lone walker otherwise in a slot of "
             "its own: its release attention underflows beside undetected slots). Written by "
             f"`{command}` in {seconds:.0f} s on {machine}.", "",
             "| model | step | observed + predicted | range | alone | row of 3 | "
             "speed ratio at 1.25 m/s | at 2 m/s | at 4 m/s |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        alone = r["cases"]["alone"]

        def ratio(speed, alone=alone, speeds=r["speeds"]):
            i = speeds.index(speed)
            return f"{alone['speed_ratio_min'][i]:.2f} to {alone['speed_ratio_max'][i]:.2f}"
        lines.append(
            f"| {name} | {r['step_s']:g} s | {r['obs_len']} + {r['pred_len']} | "
            f"{range_text(r['range'])} | {range_text(alone['range'])} | "
            f"{range_text(r['cases']['row of 3']['range'])} | {ratio(1.25)} | {ratio(2.0)} | "
            f"{ratio(4.0)} |")
    lines += ["", "Passing speeds per model (`+` passes alone and in the row, `a` alone only, "
              "`r` in the row only, `.` neither), " + f"{SPEEDS[0]:g} to {SPEEDS[-1]:g} m/s:",
              "", "```"]
    width = max(len(name) for name in rows)
    for name, r in rows.items():
        alone, row = (r["cases"][c]["passed"] for c in CASES)
        marks = "".join("+" if a and b else "a" if a else "r" if b else "."
                        for a, b in zip(alone, row))
        lines.append(f"{name:<{width}} {marks}")
    lines.append("```")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--models", nargs="+", default=None, metavar="NAME",
                        help="shipped models to measure (default: all); the output "
                        "folder's rows of the others are kept")
    add_results_flags(parser, "speed_range", "speed_range.md and .json", runs=False)
    args = parser.parse_args(argv)
    names = args.models or pretrained.available()
    out = results_folder(args)
    progress = Progress()
    load = os.getloadavg()[0]
    start = time.perf_counter()
    rows = {}
    if args.models and (out / "speed_range.json").exists():
        rows = json.loads((out / "speed_range.json").read_text())["models"]
    grids = {}
    for name in names:
        progress.line(f"measuring {name}")
        rows[name] = measure_model(name)
        grids[(rows[name]["step_s"], rows[name]["obs_len"], rows[name]["pred_len"])] = True
    for step_s, obs_len, pred_len in grids:
        baseline = f"constant velocity ({step_s:g} s, {obs_len} + {pred_len})"
        if baseline in rows:                 # kept from the output folder's record
            continue
        grid = TimeGrid(step_s=step_s, obs_len=obs_len, pred_len=pred_len)
        rows[baseline] = {
            "step_s": step_s, "obs_len": obs_len, "pred_len": pred_len,
            **measure(ConstantVelocity(obs_len, pred_len), None, grid)}
    seconds = time.perf_counter() - start
    machine = (f"{platform.machine()} with {os.cpu_count()} cores"
               f" ({jax.devices()[0].platform}; load average {load:.1f} as it started)")
    command = "python experiments/speed_range.py" + (" --publish" if args.publish else "") + (
        f" (then --models {' '.join(args.models)}, the other rows kept)" if args.models else "")
    out.mkdir(parents=True, exist_ok=True)
    record = {"rule": {"max_fde_share": MAX_FDE_SHARE,
                       "max_heading_error_deg": MAX_HEADING_ERROR_DEG,
                       "headings_deg": list(HEADINGS_DEG), "row_size": ROW_SIZE,
                       "row_spacing_m": ROW_SPACING_M},
              "seconds": round(seconds, 1), "models": rows}
    (out / "speed_range.md").write_text(markdown(rows, command, seconds, machine))
    (out / "speed_range.json").write_text(json.dumps(record, indent=1) + "\n")
    print(json.dumps(record, indent=1) if args.json else (out / "speed_range.md").read_text())


if __name__ == "__main__":
    main()
