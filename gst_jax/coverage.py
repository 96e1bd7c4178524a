"""Coverage of conformal regions over a recorded scene played as a stream (what
`python -m gst_jax.conformal` reports).

A file's frames are fed to a `gst_jax.stream.Stream` one model step at a time, from the first
frame of the split's first window to its end; every prediction is scored at horizon k when
the position k steps later is observed (`record`: once, whatever the methods). Each method
is then measured on those scores (`measure`): the online ones are fed them as they came back,
which issues exactly the radii of a stream running the method itself (tests/test_stream.py).
The first `calibration` fraction of the frames calibrates split conformal (the
ceil((n+1)(1-alpha))-th smallest of their scores, per horizon step); every method's coverage
and mean radius are then measured on the frames after it, the same predictions for all:
long-run coverage = the fraction of scored predictions whose observed position fell within
the radius issued with them; whole-horizon coverage = the fraction of predictions with every
step inside (`joint_coverage`; `simultaneous` calibrates discs for it, with
`gst_jax.conformal.simultaneous`). The command's table and figure of a result are
`gst_jax.coverage_report`'s.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import time
from typing import Iterable, Iterator, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax import conformal, data
from gst_jax.config import DataConfig
from gst_jax.data.readers import Tracks
from gst_jax.progress import Progress
from gst_jax.stream import Stream

METHODS = ("split", *conformal.ONLINE_METHODS)
ACI_GAMMA = inspect.signature(conformal.aci).parameters["gamma"].default

FrameRows = tuple[int, np.ndarray, np.ndarray]     # frame id, track ids (M,), positions (M, 2)


def frames(tracks: Tracks, first: int, last: int) -> Iterator[FrameRows]:
    """(frame id, track ids (M,), positions (M, 2)) of every step of the file's grid from
    frame `first` to `last`, steps without detections included."""
    for frame in range(first, last + 1, tracks.frame_step):
        rows = tracks.frames == frame
        yield frame, tracks.pedestrians[rows], tracks.xy[rows]


def live_tracks(frames_of_file: list[FrameRows], obs_len: int) -> int:
    """The most tracks a stream holds at once over these frames: the ids seen within any
    `obs_len` consecutive frames (a stream sized so never grows, never recompiles)."""
    seen = [set(ids.tolist()) for _, ids, _ in frames_of_file]
    return max([len(set().union(*seen[max(0, t - obs_len + 1):t + 1]))
                for t in range(len(seen))], default=1)


@dataclasses.dataclass
class Snapshot:
    """One frame's regions, for a figure: the frame after calibration predicting the most
    tracks. history (L, T, 2) NaN where not detected; futures (L, P, 2); radii (L, P);
    truth (L, P, 2) the positions observed later, NaN where not."""

    frame: int
    history: np.ndarray
    futures: np.ndarray
    radii: np.ndarray | None            # None in a recording's best frame, before measuring
    truth: np.ndarray


@dataclasses.dataclass
class Recording:
    """A stream pass over recorded frames, scored but without regions: per file with frames,
    per frame, the delayed scores and their mask (F, C, P) and the slots given to new tracks
    (F, C); `best`: what a snapshot needs of the frame after calibration predicting the most tracks
    (file, frame index, its slots (L,), and a Snapshot without radii)."""

    files: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    frames: int
    calibrating: int
    step_s: float
    best: tuple[int, int, np.ndarray, Snapshot] | None


def record(run, streams: Sequence[Iterable[FrameRows]], *, calibration: float = 0.3,
           convention: str = "gst", seed: int = 0, progress: Progress | None = None
           ) -> Recording:
    """Play the streams (iterators of frames, one after another, each a fresh stream) through
    the model once and keep every delayed score: what every method is measured on."""
    if not 0 <= calibration < 1:
        raise ValueError(f"calibration must lie in [0, 1), got {calibration}")
    recorded = [list(s) for s in streams]
    total = sum(len(s) for s in recorded)
    calibrating = round(calibration * total)
    horizon = run.model_config.pred_len
    files: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    best: tuple[int, int, np.ndarray, Snapshot] | None = None
    done = 0
    started = time.perf_counter()
    for frames_of_file in filter(None, recorded):
        # A recorded file's ids name one person each (its windows assume so too): no
        # restarts for fast movers (ETH's annotations exceed a brisk walk at 46 % of steps).
        # Every frame is the model's: a recording waits for it (no deadline).
        player = Stream(run, regions=conformal.Regions(None), convention=convention, seed=seed,
                        capacity=live_tracks(frames_of_file, run.model_config.obs_len),
                        max_speed=None, deadline_s=None)
        scores, masks, new_slots = [], [], []
        for index, (frame, ids, xy) in enumerate(frames_of_file):
            before = np.asarray(player.state.track_ids)
            out = player.step(ids, xy)
            after = np.asarray(player.state.track_ids)
            if len(after) != len(before):
                raise RuntimeError("the stream grew: live_tracks undercounted")
            assert out.delayed is not None, "a stream with regions gives delayed scores"
            scores.append(out.delayed.scores)
            masks.append(out.delayed.mask)
            new_slots.append(np.asarray(player.state.fresh))
            done += 1
            if done > calibrating and (best is None or len(out.ids) > len(best[2])):
                slots = np.array([int(np.flatnonzero(after == i)[0]) for i in out.ids], int)
                snapshot = Snapshot(frame, _histories(player, slots), out.futures, None,
                                    _truth(frames_of_file[index + 1:index + 1 + horizon],
                                           out.ids, out.futures.shape))
                best = (len(files), index, slots, snapshot)
            if progress:
                progress.count("frames", done, total, started)
        files.append((np.stack(scores), np.stack(masks), np.stack(new_slots)))
    return Recording(files, total, calibrating, run.model_config.step_s, best)


def measure(recording: Recording, method: str, alpha: float = 0.1, pooled: bool = True,
            options: tuple = (), seed: int = 0, bonferroni: bool = False
            ) -> tuple[dict, Snapshot | None]:
    """Coverage and mean radius per horizon step of `method` over a recording, on the frames
    after its calibration, and the snapshot of its best frame (None if there is none). split:
    the radii of the calibration frames' scores; aci / dtaci / pid: the recorded scores fed,
    as they came back, to the online method (`conformal.Regions(method, alpha, pooled,
    options)`), exactly as a stream with those regions would (DtACI's expert draws from
    `seed`).
    bonferroni: every horizon step aims at alpha / P, so that the P discs of a prediction hold
    together with probability at least 1 - alpha (the union bound; `joint_coverage` is that
    figure)."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    files = recording.files
    horizon = files[0][0].shape[-1] if files else 0
    flat = [(s, m) for scores, masks, _ in files for s, m in zip(scores, masks)]
    calibrating = recording.calibrating
    result = {"method": method, "alpha": alpha, "pooled": pooled, "frames": recording.frames,
              "calibration_frames": calibrating, "step_s": recording.step_s,
              "bonferroni": bonferroni}
    if bonferroni:
        alpha = alpha / max(horizon, 1)
        result["step_alpha"] = alpha
    if method == "split":
        calibration_scores = np.concatenate(                      # (P, n), NaN where none
            [np.where(m, s, np.nan).T for s, m in flat[:calibrating]] or
            [np.zeros((horizon, 0))], axis=1)
        valid = np.isfinite(calibration_scores)
        split_radii = np.asarray(jax.vmap(conformal.split_radius, (0, 0, None))(
            calibration_scores, valid, alpha))
        result["split_calibration_scores"] = int(valid[0].sum())
        issued = [np.broadcast_to(split_radii, s.shape) for s, _ in flat]
        radii_of_file = [np.broadcast_to(split_radii, f[0].shape) for f in files]
    else:
        regions = conformal.Regions(method, alpha, pooled, tuple(options))
        keys = jax.random.split(jax.random.key(seed), max(len(files), 1))
        replayed = [jax.tree.map(np.asarray, _replay(regions, key, *f))
                    for f, key in zip(files, keys)]
        radii_of_file = [radii for radii, _ in replayed]
        issued = [given for _, issued_in_file in replayed for given in issued_in_file]
    covered, counted, radii = np.zeros(horizon), np.zeros(horizon), np.zeros(horizon)
    for (scores, mask), given in list(zip(flat, issued))[calibrating:]:
        covered += np.sum(mask & (scores <= given), axis=0)
        counted += np.sum(mask, axis=0)
        radii += np.sum(np.where(mask, given, 0.0), axis=0)
    result.update(scores=counted.astype(int).tolist(),
                  coverage=(covered / np.maximum(counted, 1)).tolist(),
                  radius=(radii / np.maximum(counted, 1)).tolist())
    result.update(joint_coverage(files, issued, calibrating))
    capacity = max((f[0].shape[1] for f in files), default=1)
    result["bound"] = aci_bound(method, pooled, options, counted, capacity)
    if result["bound"] is not None:
        result["gamma"] = dict(options).get("gamma", ACI_GAMMA)
    if recording.best is None:
        return result, None
    file_index, index, slots, snapshot = recording.best
    return result, dataclasses.replace(snapshot,
                                       radii=radii_of_file[file_index][index][slots])


def joint_coverage(files, issued: list[np.ndarray], calibrating: int) -> dict:
    """Whole-horizon coverage: of the predictions made after the calibration frames whose P
    steps were all observed, the fraction with every step inside the disc issued with it (what
    a planner's safety needs), and how many such predictions there were. `issued`: the radii
    issued with each frame's delayed scores, flat over the files' frames."""
    joint, predictions, first = 0, 0, 0
    for scores, masks, _ in files:
        frames, _, horizon = scores.shape
        given = np.stack(issued[first:first + frames])
        made = np.arange(max(frames - horizon, 0))                   # predictions of frame t0
        made = made[first + made >= calibrating]
        rows = made[:, None] + np.arange(1, horizon + 1)               # (T0, P): t0 + k
        steps = np.arange(horizon)
        inside = (scores[rows, :, steps] <= given[rows, :, steps])     # (T0, P, C)
        scored = masks[rows, :, steps].all(axis=1)                     # (T0, C)
        joint += int(np.sum(inside.all(axis=1) & scored))
        predictions += int(np.sum(scored))
        first += frames
    return {"joint_coverage": joint / max(predictions, 1), "joint_predictions": predictions}


def simultaneous(recording: Recording, method: str, alpha: float = 0.1, options: tuple = (),
                 seed: int = 0) -> dict:
    """Whole-horizon discs over a recording (`conformal.simultaneous`: one score per
    prediction, the largest of its steps' errors over their scales, calibrated on the
    recording's calibration frames, then adapted online by `method`, aci, dtaci or pid, pooled
    over the tracks, DtACI's expert draws from `seed`): the method, alpha, and over the
    predictions made after the calibration frames `joint_coverage`, `joint_predictions` and
    per step the coverage and the mean radius (`coverage`, `radius`), beside what `measure`
    reports for per-step discs."""
    if method not in conformal.ONLINE_METHODS:
        raise ValueError(f"simultaneous discs take an online method "
                         f"({', '.join(conformal.ONLINE_METHODS)}), got {method!r}")
    online = conformal.ONLINE_METHODS[method](alpha, **dict(options))
    found = conformal.simultaneous(online, [(scores, masks) for scores, masks, _ in
                                            recording.files],
                                   recording.calibrating, jax.random.key(seed))
    return {"method": method, "alpha": alpha, **found}


def exchangeable_coverage(recording: Recording, alpha: float = 0.1, permutations: int = 2000,
                          seed: int = 0) -> np.ndarray:
    """What a stream's length alone allows: the whole-horizon coverage (permutations,) of
    split conformal on the recording's predictions with their frames put in random orders
    (each frame's predictions kept together), so that nothing shifts: calibrated on the first
    share of the frames that `recording.calibrating` is of all (scales and the
    ceil((n+1)(1-alpha))-th smallest score m, as `simultaneous` starts), scored on the rest.
    Split conformal is exactly valid there (mean coverage >= 1 - alpha); the spread is what
    any method's figure on a stream of this length carries."""
    blocks = []                                       # per frame t0: (C_t0, P) errors
    for scores, masks, _ in recording.files:
        frames, _, horizon = scores.shape
        for made in range(max(frames - horizon, 0)):
            errors, scored = conformal.path_errors(scores, masks, made)
            if scored.any():
                blocks.append(errors[:, scored].T)
    if len(blocks) < 2:
        return np.full(permutations, np.nan)
    calibrating = min(max(round(len(blocks) * recording.calibrating / max(recording.frames, 1)),
                          1), len(blocks) - 1)
    rng = np.random.default_rng(seed)
    covered = np.empty(permutations)
    for i in range(permutations):
        order = rng.permutation(len(blocks))
        calibration = np.concatenate([blocks[j] for j in order[:calibrating]])
        scale = conformal.path_scales(calibration)
        # conformal.split_radius in NumPy: its jnp ops would compile again for every
        # calibration size the orders give (hundreds per stream).
        rank = int(np.ceil((len(calibration) + 1) * (1 - alpha)))
        ratios = np.sort(np.max(calibration / scale, axis=1))
        q = ratios[rank - 1] if rank <= len(ratios) else np.inf
        rest = np.concatenate([blocks[j] for j in order[calibrating:]])
        covered[i] = np.mean(np.max(rest / scale, axis=1) <= q)
    return covered


def aci_bound(method: str, pooled: bool, options: tuple, counted: np.ndarray,
              capacity: int) -> list[float] | None:
    """Gibbs & Candès's finite-stream bound on |coverage - (1 - alpha)| for ACI, per horizon
    step k, over the T scores counted (a stretch of the stream, which starts at a level in
    [-gamma, 1 + gamma]): (max(alpha_s, 1 - alpha_s) + (d + 1) gamma) / (gamma T) <=
    (1 + gamma + k C gamma) / (gamma T), d <= k C - 1 the scores taken between a score's
    prediction and its return (C tracks a frame pooled, one per track: k). None for the
    other methods and for batch="mean" (whose T counts updates)."""
    settings = dict(options)
    if method != "aci" or settings.get("batch", "sequential") != "sequential":
        return None
    gamma = settings.get("gamma", ACI_GAMMA)
    ks = np.arange(1, len(counted) + 1)
    delay = ks * (capacity if pooled else 1)
    return ((1 + gamma + delay * gamma) / (gamma * np.maximum(counted, 1))).tolist()


def play(run, streams: Sequence[Iterable[FrameRows]], *, method: str, alpha: float = 0.1,
         pooled: bool = True, calibration: float = 0.3, convention: str = "gst",
         seed: int = 0, bonferroni: bool = False, progress: Progress | None = None
         ) -> tuple[dict, Snapshot | None]:
    """`record` then `measure`: coverage and mean radius per horizon step of one method."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    recording = record(run, streams, calibration=calibration, convention=convention,
                       seed=seed, progress=progress)
    return measure(recording, method, alpha, pooled, seed=seed, bonferroni=bonferroni)


@functools.partial(jax.jit, static_argnums=0)
def _replay(regions: conformal.Regions, key: jax.Array, scores: jax.Array, masks: jax.Array,
            new_slots: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The radii (F, C, P) a stream with `regions` issues at each of a file's F frames, from
    the scores that came back at each (F, C, P) (`Regions.advance` scanned over the frames),
    and the radii issued with those scores (F, C, P): horizon k's, k frames earlier."""
    frames, capacity, horizon = scores.shape
    ks = jnp.arange(1, horizon + 1)

    def step(carry, x):
        state, ring = carry                        # ring (P, C, P): radii of the last P frames
        t, score, mask, new, key = x
        issued = jnp.where(mask, ring[(t - ks) % horizon, :, ks - 1].T, 0.0)
        state, radii = regions.advance(state, key, new,
                                       conformal.DelayedScores(score, mask, issued))
        return (state, ring.at[t % horizon].set(radii)), (radii, issued)

    ring = jnp.zeros((horizon, capacity, horizon), scores.dtype)
    xs = (jnp.arange(frames), scores, masks, new_slots, jax.random.split(key, frames))
    return jax.lax.scan(step, (regions.init(capacity, horizon), ring), xs)[1]


def _histories(player: Stream, slots: np.ndarray) -> np.ndarray:
    """(L, T, 2) the observed steps of the tracks in these slots, NaN where not detected."""
    state = player.state
    positions = np.asarray(state.positions)[slots]
    return np.where(np.asarray(state.detected)[slots][..., None] > 0, positions, np.nan)


def _truth(later: list[FrameRows], ids: np.ndarray, shape: tuple) -> np.ndarray:
    """(L, P, 2) where these tracks were seen in the frames after, NaN where not."""
    truth = np.full(shape, np.nan)
    for k, (_, frame_ids, xy) in enumerate(later):
        for row, track in enumerate(ids):
            found = np.flatnonzero(frame_ids == track)
            if len(found):
                truth[row, k] = xy[found[0]]
    return truth


def scene_streams(data_config: DataConfig, split: str, grid) -> list[Iterator[FrameRows]]:
    """The frames of every file of a scene (or of your own data) that the split's windows
    cover, one iterator per file."""
    return [frames(tracks, first, last)
            for tracks, first, last in data.split_frames(data_config, split, grid)]
