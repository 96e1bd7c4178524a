"""Online corrections after a crowd changes, open loop (issue 90, part 3): each predictor's
error against the seconds since the shift, and what a step costs.

    python experiments/adaptation_shift.py --publish

Every held-out episode of the task's humans with a shift (`navigate crowds`' seeds 100-129:
1.5x faster, or ORCA to social force, from 6 s on; runs/crowds/test, made as
experiments/crowdnav_env.py says) is replayed frame by frame through a `Stream`, as a robot
that sees everyone would run it: constant velocity, the model trained on the task's humans,
and that model corrected online from its delayed scores (`gst_jax.adaptation`: the crowd's
speed scale; a recursive-least-squares blend of the model and constant velocity), and
constant velocity scaled by the speed estimate. Each prediction of a person seen at all 5
predicted steps is scored (ADE, metres) and binned by the time of its first predicted step
since the shift. A step's cost is the median wall time of `Stream.step` over the episodes
(after compiling; the machine and its load are said where the figures are published).
Writes adaptation_shift.{md,json} into runs/adaptation_shift/ (or --workdir); --publish
replaces results/adaptation_shift.{md,json}.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from _common import add_results_flags, results_folder
from gst_jax.adaptation import METHODS
from gst_jax.predictors import ConstantVelocity
from gst_jax.runs import load_model
from gst_jax.simulate.crowdnav.environment import EnvParams
from gst_jax.stream import Stream

STEP_S = EnvParams.step_s
SHIFT_AT_S = EnvParams.shift_at_s
# Bins of seconds since the shift (left edges; the last open).
BINS = (-6.0, -3.0, 0.0, 1.0, 2.0, 4.0, 8.0, 16.0)


def read_episode(path: Path) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """frame -> (ids (M,), positions (M, 2)) of a `navigate crowds` file."""
    rows = np.loadtxt(path, ndmin=2)
    frames: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for frame in np.unique(rows[:, 0]).astype(int):
        chosen = rows[rows[:, 0] == frame]
        frames[int(frame)] = (chosen[:, 1].astype(np.int32), chosen[:, 2:4])
    return frames


def replay(make_stream, frames: dict) -> tuple[list[tuple[float, float]], list[float]]:
    """(seconds since the shift, ADE) of every prediction scored, and each step's seconds."""
    stream = make_stream()
    stream.warm_up(40)
    scored, costs = [], []
    where = {f: dict(zip(ids.tolist(), map(tuple, xy))) for f, (ids, xy) in frames.items()}
    for frame in sorted(frames):
        ids, positions = frames[frame]
        started = time.perf_counter()
        out = stream.step(ids, positions)
        costs.append(time.perf_counter() - started)
        pred_len = out.futures.shape[-2] if len(out.ids) else 0
        for person, future in zip(out.ids.tolist(), out.futures):
            truth = [where.get(frame + k, {}).get(person) for k in range(1, pred_len + 1)]
            if all(t is not None for t in truth):
                error = np.linalg.norm(future - np.asarray(truth), axis=-1).mean()
                scored.append(((frame + 1) * STEP_S - SHIFT_AT_S, float(error)))
    return scored, costs


def predictors(model: str) -> dict:
    """name -> a function making a fresh stream."""
    run = load_model(model)
    cv = ConstantVelocity(obs_len=run.model_config.obs_len, pred_len=run.model_config.pred_len)
    quiet = dict(deadline_s=None)               # no fallback: the predictor itself is scored
    made = {"constant velocity": lambda: Stream(cv, step_s=STEP_S, **quiet),
            "constant velocity, speed-scale": lambda: Stream(
                cv, step_s=STEP_S, adaptation=METHODS["speed-scale"](), **quiet),
            "GST": lambda: Stream(run, **quiet)}
    for name, method in METHODS.items():
        made[f"GST, {name}"] = lambda method=method: Stream(run, adaptation=method(), **quiet)
    return made


def table(rows: list[dict]) -> str:
    heads = [f"{low:+g} to {high:+g} s" for low, high in zip(BINS, BINS[1:])] + [
        f"{BINS[-1]:+g} s on"]
    lines = ["| shift | predictor | " + " | ".join(heads) + " | step, ms (median) |",
             "|---" * (3 + len(heads)) + "|"]
    for row in rows:
        cells = [f"{m:.3f}" if m is not None else "" for m in row["ade_by_bin"]]
        lines.append(f"| {row['shift']} | {row['predictor']} | " + " | ".join(cells)
                     + f" | {row['step_ms']:.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="pretrained:crowdnav_env_partial",
                        help="the model trained on the task's humans (default: %(default)s)")
    parser.add_argument("--test-data", type=Path, default=Path("runs/crowds/test"),
                        help="the held-out episodes (default: %(default)s)")
    add_results_flags(parser, "adaptation_shift", "adaptation_shift.md and .json", runs=False)
    args = parser.parse_args(argv)
    rows = []
    for shift in ("speed", "policy"):
        episodes = [read_episode(p) for p in sorted(args.test_data.glob(f"*shift{shift}*.txt"))]
        for name, make in predictors(args.model).items():
            scored, costs = [], []
            for frames in episodes:
                s, c = replay(make, frames)
                scored += s
                costs += c[10:]                    # the first frames fill the history
            since = np.array([s for s, _ in scored])
            errors = np.array([e for _, e in scored])
            bins = np.digitize(since, BINS) - 1
            rows.append({"shift": shift, "predictor": name, "episodes": len(episodes),
                         "ade_by_bin": [float(errors[bins == b].mean()) if (bins == b).any()
                                        else None for b in range(len(BINS))],
                         "count_by_bin": [int((bins == b).sum()) for b in range(len(BINS))],
                         "step_ms": 1000 * float(np.median(costs))})
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    text = "\n".join([
        "# Online corrections after a crowd changes, open loop", "",
        f"Made by `python experiments/adaptation_shift.py --publish` (model {args.model}): "
        "held-out episodes of the task's humans with a shift at 6 s, replayed through a "
        "stream that sees everyone; ADE (m) of the predictions whose 5 steps were all "
        "observed, binned by the time of their first predicted step since the shift; the "
        "median wall time of `Stream.step` (after compiling).", "", table(rows), ""])
    out = results_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    (out / "adaptation_shift.md").write_text(text)
    (out / "adaptation_shift.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)


if __name__ == "__main__":
    main()
