"""How often `Stream`'s gate restarts a real track, and how often it catches an id given to
someone else (issue 92, item 3):

    python experiments/identity_gate.py

Every annotated triple of a person's positions at steps t - 1, t and t + k (k = 1, 2, 4: a
frame later, or after one or three missed frames) of ETH/UCY's five scenes (0.4 s steps) and of
an episode of the navigation task's humans (data/samples/crowdnav_orca, 0.25 s), judged as
`observe` judges a known id: its velocity from t - 1 and t, its new position at t + k. A real
track restarted is a false restart. Then the position at t + k is swapped for another
person's at that step (the nearest to the true one, and one drawn at random), as a tracker
that recycles or switches ids would: a restart is a catch. The default gate (MAX_SPEED,
MAX_ACCELERATION, JUMP_TOLERANCE) against the rule before issue 92 (2.5 m/s, the speed rule
alone).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gst_jax import data
from gst_jax.data.readers import Tracks, read_tracks, to_model_rate
from gst_jax.stream import JUMP_TOLERANCE, MAX_ACCELERATION, MAX_SPEED, Gate

SIM = (Path(__file__).parents[1] / "data" / "samples" / "crowdnav_orca"
       / "orca-humans20-seed101-episode0.txt")
GATES = {f"default ({MAX_SPEED:g} m/s, {MAX_ACCELERATION:g} m/s^2, {JUMP_TOLERANCE:g} m)":
         Gate(MAX_SPEED, MAX_ACCELERATION, JUMP_TOLERANCE),
         "before issue 92 (2.5 m/s alone)": Gate(2.5)}


def triples(tracks: Tracks, k: int, swap: str | None, rng) -> np.ndarray:
    """(n, 3, 2): each person's positions at t - 1, t and t + k (swap "nearest" or "random":
    the last another person's at t + k)."""
    step = tracks.frame_step
    people: dict[int, dict[int, np.ndarray]] = {}
    frames: dict[int, list[tuple[int, np.ndarray]]] = {}
    for frame, person, xy in zip(tracks.frames.tolist(), tracks.pedestrians.tolist(), tracks.xy):
        people.setdefault(person, {})[frame] = xy
        frames.setdefault(frame, []).append((person, xy))
    rows = []
    for person, seen in people.items():
        for frame, now in seen.items():
            before, later = seen.get(frame - step), seen.get(frame + k * step)
            if before is None or later is None:
                continue
            if swap is not None:
                others = np.array([xy for other, xy in frames[frame + k * step]
                                   if other != person])
                if not len(others):
                    continue
                later = (others[np.argmin(np.linalg.norm(others - later, axis=1))]
                         if swap == "nearest" else others[rng.integers(len(others))])
            rows.append((before, now, later))
    return np.array(rows).reshape(-1, 3, 2)


def restarted(rows: np.ndarray, gate: Gate, step_s: float, k: int) -> np.ndarray:
    before, now, later = rows[:, 0], rows[:, 1], rows[:, 2]
    return gate.another_person(now, (now - before) / step_s, np.ones(len(rows), bool), later,
                               np.full(len(rows), k * step_s))


def main() -> None:
    rng = np.random.default_rng(0)
    sets = {"simulated crowd": ([to_model_rate(read_tracks(SIM), 4.0, 4.0)], 0.25)}
    for scene in ("eth", "hotel", "univ", "zara1", "zara2"):
        paths = data.protocols.scene_files(data.default_data_dir(), scene)
        sets[scene] = ([read_tracks(path) for path in paths], 0.4)
    print("| gate | data | real tracks restarted, k = 1 / 2 / 4 | swapped ids caught, k = 1: "
          "nearest other / random other |")
    print("|---|---|---|---|")
    for name, gate in GATES.items():
        for scene, (files, step_s) in sets.items():
            false = []
            for k in (1, 2, 4):
                rows = np.concatenate([triples(t, k, None, rng) for t in files])
                false.append(f"{int(restarted(rows, gate, step_s, k).sum())}/{len(rows)}")
            caught = []
            for swap in ("nearest", "random"):
                rows = np.concatenate([triples(t, 1, swap, rng) for t in files])
                caught.append(f"{restarted(rows, gate, step_s, 1).mean():.3f}")
            print(f"| {name} | {scene} | {' / '.join(false)} | {' / '.join(caught)} |")


if __name__ == "__main__":
    main()
