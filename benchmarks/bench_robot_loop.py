"""A robot's loop over a tracker: warm-up, a restart from a warm compilation cache, and 400
frames of a crowd that comes and goes (`gst_jax.stream.Stream`).

    python benchmarks/bench_robot_loop.py                     # every phase below, in order
    python benchmarks/bench_robot_loop.py --phases restart --cache DIR   # one, on a cache

CrowdNav++'s predictor (`pretrained:crowdnav_sj`, steps of 0.25 s) with pooled DtACI regions
(alpha = 0.1). Each phase runs in a process of its own, so that nothing compiled by another
phase is in memory; compilations are counted with `gst_jax.compiles.count_compiles` (a
program loaded from the persistent cache counts as one).

- cold: an empty compilation cache (`Stream(compilation_cache=DIR)`); `warm_up(64)` timed and
  its programs counted; then a crowd growing from 4 to 40 people, one more every second frame
  (capacity 8 -> 48), compilations inside the loop counted (none expected) and its slowest
  step; then the tracker loop below.
- restart: a new process on the same cache: seconds from the process's start to the first
  prediction (two frames, the second predicting both people seen), split into imports,
  loading the model, and building the stream plus those two steps (what a restarted robot
  waits, its program loaded from the cache); then `warm_up(64)` from the warm cache.
- no-warm-up: another empty cache, the same growing crowd without `warm_up`: the
  compilations in the loop (one per capacity reached) and its slowest step.
- no-rule: the tracker loop with `max_speed=None` (an id is one person whatever it does), for
  the coverage and radii a recycled id costs without the rule.
- surge: a crowd that comes and goes (issue 92), on an empty cache, frames paced at the
  model's period (its step_s) as a robot's loop is: `warm_up(40)` (up to 48 slots), then 40
  walkers for 60 frames, 120 for 120 frames (128 slots: compiled in the background, constant
  velocity meanwhile, and where a step overruns the period), 40 again for 150 frames.
  Reported: the median step before, during and after, the longest frame in model periods
  (target: at most 2), the frames after the surge until the median of 10 steps is back within
  1.5x of before (target: within 100), the frames of constant velocity by reason and the
  capacities in turn.

The tracker loop: 400 frames; people enter at the edges of a 16 m square at random times
(about 50 at once at the peak), walk straight at 0.5-1.5 m/s and leave after 10-60 s. The
tracker gives a leaving person's id to the next newcomer (ids reused, often within obs_len
frames), reporting half of its lost tracks (`Stream.forget`) and recycling the others silently
(the max_speed rule must catch those); each detection is missed with probability 0.1
(occlusions) and reported as NaN with probability 0.02 (`non_finite="undetected"`); frames
come with timestamps and 2 % of them are dropped (`step(time=)` fills the gap). Reported:
how many ids the tracker gave to someone else within obs_len steps of their last holder's
last detection (reported lost, or silently), the step latency (p50, p99, max over the 400
calls of `Stream.step`, numpy in and out, after `warm_up(64)`), the compilations inside the
loop, the tracks restarted, and the pooled coverage (the fraction of scored predictions
within the radius issued with them, all horizon steps together, and the lowest and highest
per step) with the mean radius at the last step.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

PHASES = ("cold", "restart", "no-warm-up", "no-rule", "surge")
FRAMES = 400
STEP_S = 0.25
# The surge's frames: 40 walkers, 120, 40 again.
SURGE = (60, 120, 150)


def crowd(frames: int = FRAMES, seed: int = 0) -> list[tuple]:
    """The tracker's output, frame by frame: (time, ids (M,), positions (M, 2), lost ids,
    and who is who (M,), which the tracker does not know): positions NaN where a detection
    came out as NaN; frames dropped by the tracker left out."""
    rng = np.random.default_rng(seed)
    people, free_ids, next_id, next_person, out, lost = [], [], 0, 0, [], []
    for t in range(frames):
        target = min(50, 4 + t // 3) if t < 300 else 50 - (t - 300) // 4
        for person in [p for p in people if p["leaves"] <= t]:
            people.remove(person)
            free_ids.append(person["id"])
            if rng.random() < 0.5:
                lost.append(person["id"])
        while len(people) < target:
            if free_ids:
                track = free_ids.pop(0)
            else:
                track, next_id = next_id, next_id + 1
            side = rng.integers(4)
            start = rng.uniform(-8, 8, 2)
            start[side % 2] = -8 if side < 2 else 8
            heading = np.arctan2(*-start[::-1]) + rng.normal(0, 0.5)
            speed = rng.uniform(0.5, 1.5)
            people.append(dict(id=track, person=next_person, start=start, entered=t,
                               velocity=speed * np.array([np.cos(heading), np.sin(heading)]),
                               leaves=t + int(rng.integers(40, 240))))
            next_person += 1
        if rng.random() < 0.02:           # the tracker dropped this frame
            continue
        seen = [p for p in people if rng.random() > 0.1]
        ids = np.array([p["id"] for p in seen], np.int64)
        xy = np.array([p["start"] + p["velocity"] * (t - p["entered"]) * STEP_S for p in seen]
                      ).reshape(-1, 2)
        xy[rng.random(len(seen)) < 0.02] = np.nan
        out.append((t * STEP_S, ids, xy, lost, [p["person"] for p in seen]))
        lost = []
    return out


def recycled(frames: list[tuple], obs_len: int = 5) -> dict:
    """How often the tracker gave an id to someone else within obs_len steps of its last
    holder's last detection (a stream still holds that track): reported lost, or silently."""
    holder, reported, silent, forgotten = {}, 0, 0, set()
    for stamp, ids, xy, lost, people in frames:
        step = round(stamp / STEP_S)
        forgotten.update(lost)
        for track, person, seen in zip(ids.tolist(), people, np.isfinite(xy).all(axis=1)):
            if not seen:                  # a NaN detection: not a detection to the stream
                continue
            last = holder.get(track)
            if last and last[0] != person and step - last[1] < obs_len:
                reported += track in forgotten
                silent += track not in forgotten
            forgotten.discard(track)
            holder[track] = (person, step)
    return {"recycled_reported": reported, "recycled_silently": silent}


def growing(frames: int = 80) -> list[tuple[np.ndarray, np.ndarray]]:
    """A crowd growing from 4 to 40 people, one more every second frame."""
    rng = np.random.default_rng(1)
    start, velocity = rng.uniform(-6, 6, (40, 2)), rng.uniform(-1, 1, (40, 2))
    return [(np.arange(min(40, 4 + t // 2)), (start + velocity * t * STEP_S)[:min(40, 4 + t // 2)])
            for t in range(frames)]


def grow(player, count_compiles) -> dict:
    worst = 0.0
    with count_compiles() as compiles:
        for ids, xy in growing():
            started = time.perf_counter()
            player.step(ids, xy)
            worst = max(worst, time.perf_counter() - started)
    return {"loop_compiles": compiles.count, "loop_compile_s": compiles.seconds,
            "worst_step_s": worst, "capacity": player.state.capacity}


def surge_frames(step_s: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """40 straight walkers, then 80 more, then the 40 alone (`SURGE` frames each, `step_s`
    apart)."""
    rng = np.random.default_rng(2)
    start, velocity = rng.uniform(-8, 8, (120, 2)), rng.uniform(-1, 1, (120, 2))
    counts = [40] * SURGE[0] + [120] * SURGE[1] + [40] * SURGE[2]
    return [(np.arange(n), (start + velocity * t * step_s)[:n]) for t, n in enumerate(counts)]


def surge(player) -> dict:
    """The surge's frames at the model's period (a frame that overran starts the next at once):
    each `Stream.step`'s seconds, its fallback and the capacity after it."""
    seconds, fallbacks, capacities = [], {}, []
    period = player.grid.step_s
    due = time.perf_counter()
    for t, (ids, xy) in enumerate(surge_frames(period)):
        time.sleep(max(0.0, due - time.perf_counter()))
        started = time.perf_counter()
        out = player.step(ids, xy)
        seconds.append(time.perf_counter() - started)
        due = started + period
        if out.fallback:
            fallbacks[out.fallback] = fallbacks.get(out.fallback, 0) + 1
        if not capacities or capacities[-1][1] != player.state.capacity:
            capacities.append((t, player.state.capacity))
    ms = 1e3 * np.array(seconds)
    end = SURGE[0] + SURGE[1]
    before = float(np.median(ms[10:SURGE[0]]))
    back = next((k for k in range(SURGE[2] - 9)
                 if np.median(ms[end + k:end + k + 10]) <= 1.5 * before), None)
    return {"before_median_ms": before, "surge_median_ms": float(np.median(ms[SURGE[0]:end])),
            "after_median_ms": float(np.median(ms[end + 100:])), "max_ms": float(ms.max()),
            "max_frame": int(ms.argmax()), "max_periods": float(ms.max() / 1e3 / period),
            "frames_back_within_1_5x": back, "longest_within_2_periods": bool(
                ms.max() <= 2e3 * period), "back_within_100_frames": back is not None
            and back <= 100, "fallback_frames": fallbacks, "capacities": capacities,
            "compiled_s": {str(c): round(s, 2)
                           for c, s in player._slots._programs.compiled.items()},
            "overruns": player.overruns}


def tracker_loop(player, count_compiles) -> dict:
    seconds, radius = [], []
    horizon = player.model.config.pred_len
    per_step_covered, per_step_scored = np.zeros(horizon), np.zeros(horizon)
    restarted = 0
    with count_compiles() as compiles:
        for stamp, ids, xy, lost, _ in crowd():
            started = time.perf_counter()
            player.forget(lost)
            out = player.step(ids, xy, time=stamp)
            seconds.append(time.perf_counter() - started)
            restarted += len(out.restarted)
            mask = out.delayed.mask
            hit = mask & (out.delayed.scores <= out.delayed.issued)
            per_step_covered += hit.sum(axis=0)
            per_step_scored += mask.sum(axis=0)
            radius.extend(out.delayed.issued[mask[:, -1], -1].tolist())
    coverage = per_step_covered / np.maximum(per_step_scored, 1)
    ms = 1e3 * np.array(seconds)
    return {**recycled(crowd(), player.model.config.obs_len),
            "p50_ms": float(np.percentile(ms, 50)), "p99_ms": float(np.percentile(ms, 99)),
            "max_ms": float(ms.max()), "loop_compiles": compiles.count, "restarts": restarted,
            "coverage": float(per_step_covered.sum() / per_step_scored.sum()),
            "coverage_min": float(coverage.min()), "coverage_max": float(coverage.max()),
            "scores": int(per_step_scored.sum()),
            "last_step_radius_m": float(np.mean(radius)) if radius else None}


def phase(name: str, model: str, cache: str) -> dict:
    """One phase, in this process (a child of `main`)."""
    imported = time.perf_counter()
    from gst_jax.compiles import count_compiles
    from gst_jax.conformal import Regions
    from gst_jax.runs import load_model
    from gst_jax.stream import Stream
    result = {"imports_s": time.perf_counter() - imported}
    loading = time.perf_counter()
    run = load_model(model)
    result["load_s"] = time.perf_counter() - loading
    regions = Regions("dtaci", 0.1)
    building = time.perf_counter()
    player = Stream(run, regions=regions, compilation_cache=cache, non_finite="undetected",
                    max_speed=None if name == "no-rule" else 2.5)
    if name == "restart":
        player.step([0, 1], [[0.0, 0.0], [1.0, 1.0]])          # seen once: not predicted yet
        out = player.step([0, 1], [[0.2, 0.0], [1.0, 1.2]])
        result.update(first_step_s=time.perf_counter() - building, first_ids=len(out.ids),
                      first_prediction_at=time.time())
        player = Stream(run, regions=regions, non_finite="undetected")
    if name == "surge":
        warming = time.perf_counter()
        result["capacities"] = list(player.warm_up(40))
        result["warm_up_s"] = time.perf_counter() - warming
        result["surge"] = surge(player)
        return result
    if name != "no-warm-up":
        with count_compiles() as compiles:
            warming = time.perf_counter()
            result["capacities"] = list(player.warm_up(64))
            result.update(warm_up_s=time.perf_counter() - warming,
                          warm_up_programs=compiles.count, warm_up_compile_s=compiles.seconds)
    if name in ("cold", "no-warm-up"):
        result["growth"] = grow(player, count_compiles)
    if name in ("cold", "no-rule"):
        player = Stream(run, regions=regions, non_finite="undetected",
                        max_speed=None if name == "no-rule" else 2.5)
        player.warm_up(64)
        result["tracker"] = tracker_loop(player, count_compiles)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="pretrained:crowdnav_sj")
    parser.add_argument("--phases", nargs="*", choices=PHASES, default=list(PHASES))
    parser.add_argument("--cache", default=None, help="the compilation cache of cold and "
                        "restart (default: a new temporary folder)")
    parser.add_argument("--child", default=None, choices=PHASES, help=argparse.SUPPRESS)
    parser.add_argument("--note", default="", help="recorded with the rows (e.g. the load)")
    args = parser.parse_args()
    if args.child:
        print(json.dumps(phase(args.child, args.model, args.cache)))
        return
    from common import print_table, record

    scratch = tempfile.mkdtemp(prefix="bench_robot_loop_")
    cache = args.cache or os.path.join(scratch, "cache")
    rows = []
    for name in args.phases:
        folder = os.path.join(scratch, name) if name in ("no-warm-up", "surge") else cache
        spawned = time.time()
        child = subprocess.run([sys.executable, __file__, "--child", name, "--model",
                                args.model, "--cache", folder], capture_output=True, text=True)
        if child.returncode:
            raise SystemExit(f"phase {name} failed:\n{child.stderr[-3000:]}")
        result = json.loads(child.stdout.strip().splitlines()[-1])
        if "first_prediction_at" in result:      # from the process's start, imports included
            result["since_start_s"] = result.pop("first_prediction_at") - spawned
        print(f"{name}: {json.dumps(result)}", flush=True)
        rows.append(record("robot_loop", phase=name, model=args.model, note=args.note,
                           **result))
    print_table([{"phase": r["phase"], **r.get("tracker", {}),
                  "warm_up_s": r.get("warm_up_s"), "first_step_s": r.get("first_step_s"),
                  "since_start_s": r.get("since_start_s")} for r in rows],
                ["phase", "warm_up_s", "first_step_s", "since_start_s", "p50_ms", "p99_ms",
                 "max_ms", "loop_compiles", "restarts", "coverage", "last_step_radius_m"])


if __name__ == "__main__":
    main()
