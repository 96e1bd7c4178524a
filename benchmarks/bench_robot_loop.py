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
- tracker: a tracker's feeds at other rates than the model's (issue 92's targets), each
  `Stream` with the default gate and `deadline_s=None` (every frame waits for the model: these
  figures are not timings); (1) and (3) over 60 s of 20 straight walkers at 0.5-1.5 m/s.
  (1) A 5 Hz tracker with `step(time=)` against a 4 Hz feed without times: the largest
  distance between their predictions at the same model steps (target: within 0.05 m).
  (2) 120 s of 40 wandering walkers (a straight walker's error is the same at every step, so
  pooled discs cover whole walkers; a person's error varies over time): heading turning at a
  rate redrawn every 2-4 s from N(0, 0.3 rad/s), speed 0.5-1.5 m/s varying by up to 10 %,
  exact paths on a 0.01 s grid; a 10 Hz tracker, stamps
  +-20 ms off the 0.1 s grid, 3 % of frames dropped: the frames refused (target 0) and the
  truth coverage, the fraction of predicted steps whose true position (the walks' at that
  step's time) lies within the radius issued (target within 0.02 of 0.9; the stream's own
  coverage, against the resampled detections, beside it); again with positions off by 3 cm
  (normal, per axis; the model's own errors already make the discs 0.7 m wide). (3) A
  3 m/s jogger and a 6 m/s cyclist among the walkers, a 4 Hz feed and the 10 Hz one: the
  fraction of frames from their second detection on (with times: from the frame that reaches
  the model's second step) in which they are predicted (target 1.0).

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

PHASES = ("cold", "restart", "no-warm-up", "no-rule", "surge", "tracker")
FRAMES = 400
STEP_S = 0.25
# The surge's frames: 40 walkers, 120, 40 again.
SURGE = (60, 120, 150)
# The tracker phase's feeds: seconds, walkers, the 10 Hz tracker's jitter (s), dropped frames
# and measurement noise (m, per axis).
FEED_S, WALKERS, JITTER_S, DROPPED, NOISE_M = 60.0, 20, 0.02, 0.03, 0.03
# The jittered feed's wandering walkers: seconds, walkers, the turn rate's spread (rad/s),
# redrawn every 2-4 s, and the time resolution of their exact paths (s).
WANDER_S, WANDERERS, TURN_RAD_S, WANDER_DT_S = 120.0, 40, 0.3, 0.01


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


def walks(count: int, seed: int, fast: tuple[float, ...] = ()):
    """`count` people walking straight across a 16 m square at 0.5-1.5 m/s, then one at each
    speed of `fast` (m/s): their exact positions (N, 2) at any time t (s)."""
    rng = np.random.default_rng(seed)
    speed = np.concatenate([rng.uniform(0.5, 1.5, count), fast])
    heading = rng.uniform(-np.pi, np.pi, len(speed))
    start = rng.uniform(-8, 8, (len(speed), 2))
    velocity = speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    return lambda t: start + velocity * t


def wandering(count: int, seed: int, seconds: float):
    """`count` people whose heading turns at a rate redrawn every 2-4 s from N(0, TURN_RAD_S)
    and whose speed (0.5-1.5 m/s each) varies by up to 10 % over 5-15 s: their exact positions
    (N, 2) at any time t in [-1, seconds + 10] (s), from paths integrated every WANDER_DT_S
    and interpolated between (the tracker's frames and the model's steps alike)."""
    rng = np.random.default_rng(seed)
    t = np.arange(-1.0, seconds + 10.0 + WANDER_DT_S, WANDER_DT_S)            # (T,)
    turn = np.empty((count, len(t)))
    for person in range(count):
        changes = t[0] + np.cumsum(rng.uniform(2.0, 4.0, int(len(t) * WANDER_DT_S / 2) + 2))
        rates = rng.normal(0.0, TURN_RAD_S, len(changes) + 1)
        turn[person] = rates[np.searchsorted(changes, t)]
    heading = rng.uniform(-np.pi, np.pi, (count, 1)) + np.cumsum(turn, axis=1) * WANDER_DT_S
    period, phase = rng.uniform(5.0, 15.0, (count, 1)), rng.uniform(0, 2 * np.pi, (count, 1))
    speed = rng.uniform(0.5, 1.5, (count, 1)) * (1 + 0.1 * np.sin(2 * np.pi * t / period
                                                                  + phase))
    step = speed[..., None] * np.stack([np.cos(heading), np.sin(heading)], -1) * WANDER_DT_S
    path = np.concatenate([np.zeros((count, 1, 2)), np.cumsum(step[:, :-1], axis=1)], axis=1)
    path += rng.uniform(-8, 8, (count, 1, 2))                                   # (N, T, 2)

    def positions_at(when: float) -> np.ndarray:
        low, share = divmod((when - t[0]) / WANDER_DT_S, 1.0)
        return (1 - share) * path[:, int(low)] + share * path[:, int(low) + 1]
    return positions_at


def feed(positions_at, rate_hz: float, seed: int, jitter_s: float = 0.0, dropped: float = 0.0,
         noise_m: float = 0.0, seconds: float = FEED_S
         ) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """A tracker's frames over `seconds` at `rate_hz`: (time, ids (N,), positions (N, 2)),
    each frame stamped with the time it was measured at, up to `jitter_s` off its rate's grid,
    a fraction `dropped` of the frames (never the first) left out, positions off by normal
    noise of `noise_m` per axis."""
    rng = np.random.default_rng(seed)
    count = int(round(seconds * rate_hz)) + 1
    times = np.arange(count) / rate_hz + rng.uniform(-jitter_s, jitter_s, count)
    kept = (rng.random(count) >= dropped) | (np.arange(count) == 0)
    frames = []
    for t in times[kept]:
        xy = positions_at(t)
        frames.append((float(t), np.arange(len(xy)), xy + rng.normal(0, noise_m, xy.shape)))
    return frames


def resampled(make_stream) -> dict:
    """(1) A 5 Hz tracker with times against a 4 Hz feed of the same walkers without: the
    largest distance between their predictions (and radii) at the same model steps."""
    positions_at = walks(WALKERS, seed=3)
    reference = make_stream()
    expected = [reference.step(ids, xy) for _, ids, xy in feed(positions_at, 4.0, seed=0)]
    player = make_stream()
    distance, radius, steps, same_ids = 0.0, 0.0, 0, True
    for t, ids, xy in feed(positions_at, 5.0, seed=0):
        out = player.step(ids, xy, time=t)
        if out.repeated:
            continue
        other = expected[round(out.time / player.grid.step_s)]
        same_ids &= sorted(out.ids.tolist()) == sorted(other.ids.tolist())
        mine, theirs = np.argsort(out.ids), np.argsort(other.ids)
        if len(mine) and len(mine) == len(theirs):
            distance = max(distance, float(np.linalg.norm(
                out.futures[mine] - other.futures[theirs], axis=-1).max()))
            radius = max(radius, float(np.abs(out.radii[mine] - other.radii[theirs]).max()))
        steps += 1
    return {"max_distance_m": distance, "max_radius_difference_m": radius,
            "steps_compared": steps, "same_ids": bool(same_ids)}


def jittered(make_stream, noise_m: float) -> dict:
    """(2) A 10 Hz tracker of WANDERERS wandering walkers for WANDER_S, jittered, dropping
    frames, its positions off by `noise_m`: the frames refused and the discs' coverage of the
    walkers' true positions at the predicted
    steps' times (pooled, per horizon step, and per 10 s of the feed), with the stream's own
    (its delayed scores, against the resampled detections) beside it."""
    from gst_jax.errors import DataError

    positions_at = wandering(WANDERERS, seed=4, seconds=WANDER_S)
    frames = feed(positions_at, 10.0, seed=1, jitter_s=JITTER_S, dropped=DROPPED,
                  noise_m=noise_m, seconds=WANDER_S)
    player = make_stream()
    step_s, horizon = player.grid.step_s, player.grid.pred_len
    refused, covered, predicted = 0, np.zeros(horizon), np.zeros(horizon)
    own_covered, own_scored, radius = 0, 0, []
    by_10_s = np.zeros((int(WANDER_S // 10) + 1, 2))             # covered, predicted
    for t, ids, xy in frames:
        try:
            out = player.step(ids, xy, time=t)
        except DataError:
            refused += 1
            continue
        if out.repeated or not len(out.ids):
            continue
        truth = np.stack([positions_at(out.time + (k + 1) * step_s)[out.ids]
                          for k in range(horizon)], axis=1)                   # (L, P, 2)
        hit = np.linalg.norm(out.futures - truth, axis=-1) <= out.radii        # (L, P)
        covered += hit.sum(axis=0)
        by_10_s[int((out.time - frames[0][0]) // 10)] += hit.sum(), hit.size
        predicted += len(out.ids)
        mask = out.delayed.mask
        own_covered += int((mask & (out.delayed.scores <= out.delayed.issued)).sum())
        own_scored += int(mask.sum())
        radius.extend(out.radii[:, -1].tolist())
    per_step = covered / np.maximum(predicted, 1)
    return {"frames": len(frames), "frames_dropped": int(round(WANDER_S * 10)) + 1 - len(frames),
            "refused": refused, "truth_coverage": float(covered.sum() / predicted.sum()),
            "truth_coverage_per_step": [round(float(c), 4) for c in per_step],
            "truth_coverage_min": float(per_step.min()),
            "truth_coverage_max": float(per_step.max()), "predicted_steps": int(predicted.sum()),
            "truth_coverage_by_10_s": [round(float(c / max(n, 1)), 4) for c, n in by_10_s
                                       if n],
            "own_coverage": own_covered / max(own_scored, 1),
            "last_step_radius_m": float(np.mean(radius))}


def fast_movers(make_stream) -> dict:
    """(3) A 3 m/s jogger and a 6 m/s cyclist among the walkers, a 4 Hz feed without times and
    the jittered 10 Hz one with (3 cm noise): the fraction of frames from their second
    detection on (with times, from the frame that reaches the model's second step) in which
    each is predicted."""
    positions_at = walks(WALKERS, seed=5, fast=(3.0, 6.0))
    jogger, cyclist = WALKERS, WALKERS + 1
    result = {}
    for name, frames, timed in (
            ("4_hz", feed(positions_at, 4.0, seed=2), False),
            ("10_hz", feed(positions_at, 10.0, seed=3, jitter_s=JITTER_S, dropped=DROPPED,
                           noise_m=NOISE_M), True)):
        player = make_stream()
        counted, seen = 0, {jogger: 0, cyclist: 0}
        for n, (t, ids, xy) in enumerate(frames):
            out = player.step(ids, xy, time=t if timed else None)
            if (out.time < frames[0][0] + player.grid.step_s - 1e-9) if timed else n < 1:
                continue
            counted += 1
            for person in seen:
                seen[person] += person in out.ids
        result[name] = {"frames": counted, "jogger": seen[jogger] / counted,
                        "cyclist": seen[cyclist] / counted, "restarts": player.restarts}
    return result


def tracker_feeds(make_stream) -> dict:
    """The tracker phase's three measurements, each figure with its target and whether it met
    it (`checks`: figure, value, target, pass)."""
    load = os.getloadavg()
    same, fast = resampled(make_stream), fast_movers(make_stream)
    exact, noisy = jittered(make_stream, 0.0), jittered(make_stream, NOISE_M)
    lowest = min(fast[feed][who] for feed in fast for who in ("jogger", "cyclist"))
    checks = [
        ("5 Hz with time= against a 4 Hz feed: largest distance between predictions (m)",
         same["max_distance_m"], "<= 0.05", same["max_distance_m"] <= 0.05),
        ("10 Hz, +-20 ms, 3 % dropped, 40 wandering walkers: frames refused",
         exact["refused"] + noisy["refused"], "0", exact["refused"] + noisy["refused"] == 0),
        ("10 Hz, +-20 ms, 3 % dropped: truth coverage at alpha 0.1", exact["truth_coverage"],
         "0.88-0.92", abs(exact["truth_coverage"] - 0.9) <= 0.02),
        ("the same, positions off by 3 cm: truth coverage", noisy["truth_coverage"],
         "0.88-0.92", abs(noisy["truth_coverage"] - 0.9) <= 0.02),
        ("3 m/s jogger, 6 m/s cyclist: lowest fraction of frames predicted from the second "
         "detection on (4 Hz and 10 Hz feeds)", lowest, "1.0", lowest == 1.0)]
    return {"load_average": [round(x, 2) for x in load], "resampled_5_hz": same,
            "jittered_10_hz": exact, "jittered_10_hz_noisy": noisy, "fast_movers": fast,
            "checks": [dict(figure=f, value=v, target=t, passed=bool(ok))
                       for f, v, t, ok in checks]}


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
    gate = {"max_speed": None if name == "no-rule" else 2.5}
    player = Stream(run, regions=regions, compilation_cache=cache, non_finite="undetected",
                    **gate)
    if name == "restart":
        player.step([0, 1], [[0.0, 0.0], [1.0, 1.0]])          # seen once: not predicted yet
        out = player.step([0, 1], [[0.2, 0.0], [1.0, 1.2]])
        result.update(first_step_s=time.perf_counter() - building, first_ids=len(out.ids),
                      first_prediction_at=time.time())
        # The stream cold's warm_up compiled (the same gate), so that its programs are read
        # from the cache: a stream of another gate is another program.
        player = Stream(run, regions=regions, non_finite="undetected", **gate)
    if name == "tracker":
        result["feeds"] = tracker_feeds(lambda: Stream(
            run, regions=regions, compilation_cache=cache, deadline_s=None))
        return result
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
        player = Stream(run, regions=regions, non_finite="undetected", **gate)
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
        folder = (os.path.join(scratch, name) if name in ("no-warm-up", "surge", "tracker")
                  else cache)
        spawned = time.time()
        child = subprocess.run([sys.executable, __file__, "--child", name, "--model",
                                args.model, "--cache", folder], capture_output=True, text=True)
        if child.returncode:
            raise SystemExit(f"phase {name} failed:\n{child.stderr[-3000:]}")
        result = json.loads(child.stdout.strip().splitlines()[-1])
        if "first_prediction_at" in result:      # from the process's start, imports included
            result["since_start_s"] = result.pop("first_prediction_at") - spawned
        print(f"{name}: {json.dumps(result)}", flush=True)
        for check in result.get("feeds", {}).get("checks", []):
            print(f"  {check['figure']}: {check['value']:.4g} (target {check['target']}): "
                  f"{'PASS' if check['passed'] else 'FAIL'}", flush=True)
        rows.append(record("robot_loop", phase=name, model=args.model, note=args.note,
                           **result))
    print_table([{"phase": r["phase"], **r.get("tracker", {}),
                  "warm_up_s": r.get("warm_up_s"), "first_step_s": r.get("first_step_s"),
                  "since_start_s": r.get("since_start_s")} for r in rows],
                ["phase", "warm_up_s", "first_step_s", "since_start_s", "p50_ms", "p99_ms",
                 "max_ms", "loop_compiles", "restarts", "coverage", "last_step_radius_m"])


if __name__ == "__main__":
    main()
