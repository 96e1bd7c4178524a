"""Padding windows into `SceneBatch`es: N rounded up to a few bucket sizes (numpy only).

Each (B, N) shape is one compiled program, so the sizes are few. A training step is a
`PackedStep`: its windows in micro-batches, each padded only to its own size bucket.
"""

from __future__ import annotations

from typing import Iterator, NamedTuple, Sequence

import numpy as np

from gst_jax.config import TimeGrid
from gst_jax.data.batch import SceneBatch, node_mask_from_positions
from gst_jax.data.windows import Window, WindowSet

# Pedestrian-slot sizes of evaluation and prediction batches; ETH/UCY windows hold 1-93
# pedestrians. Few sizes: a planner whose crowd changes size meets few compiled programs.
BUCKETS = (8, 16, 24, 32, 48, 64, 96, 128)
# Training: every 8 slots, because a large window costs ~N^3 (each target's attention over
# its N + 1 neighbours) and trains in a micro-batch of its own (see `pack_step`).
TRAINING_BUCKETS = tuple(range(8, 129, 8))
# Windows of up to this many pedestrians share one micro-batch of the step; larger ones
# train one per micro-batch. Below it a call's fixed cost outweighs its padding; above it,
# padding a 25-pedestrian window to 96 slots would cost 60 times its own work.
SHARED_MICRO_BATCH_MAX = 24
# Evaluation batches hold B scenes of N slots with B N^2 <= this (16 scenes of 32): few
# programs, and memory bounded by the padded edges whatever the crowd.
EDGE_BUDGET = 16 * 32 * 32


class PackedStep(NamedTuple):
    """One optimiser step: its windows in micro-batches, each padded to its own bucket.

    micro_batches: SceneBatches whose window_index name the step's windows (each once).
    num_scenes: the step's real windows; the step's loss is their mean (docs/MODEL.md 3).
    """

    micro_batches: tuple[SceneBatch, ...]
    num_scenes: int


def bucket_size(num_pedestrians: int, buckets: Sequence[int] = BUCKETS) -> int:
    """The smallest bucket holding `num_pedestrians`; beyond the largest, the buckets go on
    in steps of its last gap (one more compiled program per size met)."""
    for size in buckets:
        if num_pedestrians <= size:
            return size
    gap = buckets[-1] - buckets[-2]
    return buckets[-1] + -(-(num_pedestrians - buckets[-1]) // gap) * gap


def pad_windows(windows: Sequence[Window], num_pedestrians: int, batch_size: int | None = None,
                window_index: Sequence[int] | np.ndarray | None = None, *,
                predicted_slots: int | None = None, observed_only: bool = False) -> SceneBatch:
    """Stack windows into a SceneBatch of N = num_pedestrians slots and B = batch_size scenes.

    Missing scenes (when batch_size > len(windows)) are all-zero with scene_mask 0.
    predicted_slots: P, the slots the prediction steps compute on (at least every window's
    `num_predicted`); None: all N. observed_only: leave out each window's pedestrians that
    are seen only after the observation (training: they add nothing to the loss).
    """
    batch_size = batch_size or len(windows)
    seq_len = windows[0].position_mask.shape[0] if windows else 1
    positions = np.zeros((batch_size, seq_len, num_pedestrians, 2), np.float32)
    position_mask = np.zeros((batch_size, seq_len, num_pedestrians), np.float32)
    for b, window in enumerate(windows):
        n = window.num_observed if observed_only else window.num_pedestrians
        if n > num_pedestrians or (predicted_slots or n) < window.num_predicted:
            raise ValueError(f"a window of {n} pedestrians ({window.num_predicted} predicted) "
                             f"does not fit {num_pedestrians} slots ({predicted_slots} predicted)")
        positions[b, :, :n] = window.positions[:, :n]
        position_mask[b, :, :n] = window.position_mask[:, :n]
    scene_mask = (np.arange(batch_size) < len(windows)).astype(np.float32)
    index = np.full(batch_size, -1, np.int32)
    index[:len(windows)] = window_index if window_index is not None else np.arange(len(windows))
    batch = SceneBatch(positions=positions, position_mask=position_mask,
                       node_mask=node_mask_from_positions(position_mask), scene_mask=scene_mask,
                       window_index=index)
    if predicted_slots is not None and windows:
        keep = batch.predicted_mask(windows[0].obs_len)[:, :predicted_slots]
        batch = batch._replace(predicted_slots=keep)
    return batch


def training_batches(window_set: WindowSet, *, batch_size: int = 16, seed: int = 0,
                     epoch: int = 0, slots_multiple: int = 1, one_micro_batch: bool = False,
                     first_step: int = 0) -> Iterator[PackedStep]:
    """One packed step per optimiser step: shuffled windows taken `batch_size` at a time.

    As in the release, a step averages `batch_size` randomly drawn scenes (the last step of
    an epoch fewer). The order is a function of (seed, epoch) only, so a resumed run sees
    the same steps. slots_multiple: every micro-batch holds a multiple of this many scenes
    (the devices it is split over; see `pack_step`). one_micro_batch: every step in one
    micro-batch padded to the set's largest window (a GPU, where a call costs more than
    padding): one program per run. first_step: the steps from this one on (a resume inside
    the epoch).
    """
    pad_to = None
    if one_micro_batch and len(window_set):
        pad_to = bucket_size(max(w.num_observed for w in window_set.windows), TRAINING_BUCKETS)
    order = np.random.default_rng([seed, epoch]).permutation(len(window_set))
    for start in range(first_step * batch_size, len(order), batch_size):
        chosen = order[start:start + batch_size]
        yield pack_step([window_set[i] for i in chosen], chosen, batch_size, slots_multiple,
                        pad_to=pad_to)


def pack_step(windows: Sequence[Window], window_index: Sequence[int] | np.ndarray,
              shared_slots: int = 16, slots_multiple: int = 1, *,
              pad_to: int | None = None) -> PackedStep:
    """A step's windows in micro-batches: those of up to SHARED_MICRO_BATCH_MAX observed
    pedestrians together in one batch of `shared_slots` scenes padded to the largest of them,
    each larger window alone, padded to its TRAINING_BUCKETS size. The programs of an epoch
    are thus one per (bucket, predicted bucket, 1) and per small bucket: a fixed, small set.

    Pedestrians seen only after the observation are left out (they add nothing to the loss),
    and the prediction steps compute on the slots of the predicted pedestrians only
    (`SceneBatch.predicted_slots`): a large window costs ~N^3, so this is most of the work.

    slots_multiple > 1 (scenes split over that many devices): every micro-batch holds a
    multiple of it; the larger windows go in groups of that many, by size, each group
    padded to the bucket of its largest.

    pad_to: instead, all windows in one micro-batch of `pad_to` slots, all of them predicted.
    """
    if pad_to is not None:
        slots = _round_up(max(shared_slots, len(windows)), slots_multiple)
        return PackedStep((pad_windows(windows, pad_to, slots, window_index,
                                       predicted_slots=pad_to, observed_only=True),),
                          len(windows))
    small = [k for k, w in enumerate(windows) if w.num_observed <= SHARED_MICRO_BATCH_MAX]
    large = [k for k, w in enumerate(windows) if w.num_observed > SHARED_MICRO_BATCH_MAX]

    def padded(group: list[int], slots: int) -> SceneBatch:
        chosen = [windows[k] for k in group]
        size = bucket_size(max(w.num_observed for w in chosen), TRAINING_BUCKETS)
        predicted = bucket_size(max(w.num_predicted for w in chosen), TRAINING_BUCKETS)
        return pad_windows(chosen, size, slots, [window_index[k] for k in group],
                           predicted_slots=min(predicted, size), observed_only=True)

    micro_batches = []
    if small:
        micro_batches.append(padded(small, _round_up(max(shared_slots, len(small)),
                                                     slots_multiple)))
    if slots_multiple > 1:              # similar sizes share a group: less padding
        large.sort(key=lambda k: windows[k].num_observed)
    for start in range(0, len(large), slots_multiple):
        micro_batches.append(padded(large[start:start + slots_multiple], slots_multiple))
    return PackedStep(tuple(micro_batches), len(windows))


def _round_up(size: int, multiple: int) -> int:
    """The smallest multiple of `multiple` that is at least `size`."""
    return -(-size // multiple) * multiple


def evaluation_batches(window_set: WindowSet, *, edge_budget: int = EDGE_BUDGET,
                       buckets: Sequence[int] = BUCKETS,
                       batch_multiple: int = 1) -> Iterator[SceneBatch]:
    """Every window once, grouped by bucket (and the bucket of its predicted pedestrians,
    `SceneBatch.predicted_slots`), B = max(1, edge_budget // N^2) scenes per batch, or for
    a bucket of fewer windows than that the next power of two of their count (rounded up to
    a multiple of `batch_multiple`: the devices the batch is split over).

    A 90-pedestrian window never shares a padded size with an 8-pedestrian one, and B N^2
    stays within the budget; `window_index` maps each scene back to `window_set`. One batch
    shape per bucket; a validation split of three windows is predicted in a batch of 4
    scenes, not of 256 (4.4 s against the 0.1 s it needs, at the test suite's XLA level).
    """
    by_bucket: dict[tuple[int, int], list[int]] = {}
    for index, window in enumerate(window_set.windows):
        size = bucket_size(window.num_pedestrians, buckets)
        predicted = min(bucket_size(window.num_predicted, buckets), size)
        by_bucket.setdefault((size, predicted), []).append(index)
    for size, predicted in sorted(by_bucket):
        indices = by_bucket[size, predicted]
        fewer = 1 << (len(indices) - 1).bit_length()          # the next power of two
        batch_size = _round_up(min(max(1, edge_budget // size ** 2), fewer), batch_multiple)
        for start in range(0, len(indices), batch_size):
            chosen = indices[start:start + batch_size]
            yield pad_windows([window_set[i] for i in chosen], size, batch_size, chosen,
                              predicted_slots=predicted)


# Positions are float32 inside the model: up to 10 km from the origin they keep millimetres.
LARGEST_COORDINATE = 1e4


def make_batch(observed_xy: np.ndarray, *, grid: TimeGrid = TimeGrid(),
               pad_to_bucket: bool = True) -> SceneBatch:
    """A prediction batch from observations (B, T_obs, N, 2), NaN where nobody was detected.

    This is the robot's use: feed the last T_obs = `grid.obs_len` tracked positions (one model
    step apart, metres in a local frame) of everyone in view; `grid` is the model's. With
    `pad_to_bucket` the pedestrian axis is padded (with undetected slots) to the next bucket
    size, so a planner whose crowd changes size reuses a few compiled programs; pedestrian k
    keeps slot k.
    """
    xy = np.asarray(observed_xy, dtype=np.float64)
    if xy.ndim != 4 or xy.shape[-1] != 2:
        raise ValueError(f"observed_xy must have shape (B, T_obs, N, 2), got {xy.shape}")
    if 0 in xy.shape:
        raise ValueError(f"observed_xy has an empty axis: shape {xy.shape}")
    if xy.shape[1] != grid.obs_len:
        raise ValueError(f"observed_xy has {xy.shape[1]} steps; the model observes the last "
                         f"obs_len = {grid.obs_len} ({grid.step_s:g} s apart): pass "
                         f"observed_xy[:, -{grid.obs_len}:]")
    if np.nanmax(np.abs(xy), initial=0.0) > LARGEST_COORDINATE:
        raise ValueError(f"observed_xy has coordinates beyond {LARGEST_COORDINATE:.0e} m, where "
                         "float32 loses millimetres: subtract a local origin first")
    missing = np.isnan(xy)
    half = missing[..., 0] != missing[..., 1]
    if half.any():
        b, t, n = np.argwhere(half)[0]
        raise ValueError(f"observed_xy[{b}, {t}, {n}] has one NaN coordinate; mark a missing "
                         "detection with NaN in both x and y")
    if np.isinf(xy).any():
        b, t, n = np.argwhere(np.isinf(xy).any(-1))[0]
        raise ValueError(f"observed_xy[{b}, {t}, {n}] is infinite")
    position_mask = (~missing[..., 0]).astype(np.float32)
    empty = np.flatnonzero(position_mask.sum(axis=(1, 2)) == 0)
    if len(empty):
        raise ValueError(f"scene(s) {empty.tolist()} have no detected pedestrian (all NaN)")
    batch_size = xy.shape[0]
    if pad_to_bucket:
        extra = bucket_size(xy.shape[2]) - xy.shape[2]
        xy = np.pad(xy, [(0, 0), (0, 0), (0, extra), (0, 0)])
        missing = np.pad(missing, [(0, 0), (0, 0), (0, extra), (0, 0)], constant_values=True)
        position_mask = np.pad(position_mask, [(0, 0), (0, 0), (0, extra)])
    return SceneBatch(positions=np.where(missing, 0.0, xy).astype(np.float32),
                      position_mask=position_mask,
                      node_mask=node_mask_from_positions(position_mask),
                      scene_mask=np.ones(batch_size, np.float32),
                      window_index=np.arange(batch_size, dtype=np.int32))
