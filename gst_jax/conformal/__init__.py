"""Calibrated uncertainty discs around predicted positions, online: split, ACI, DtACI, PID.

A predictor gives, at every time step t and for every tracked person, positions for horizon
steps k = 1..P. The nonconformity score of the horizon-k prediction made at t is the distance
`s = ||predicted_t[k] - observed_{t+k}||`, known k steps later. A region is a disc of radius r
around the predicted position; it covers when `s <= r`. Each method below turns the scores
seen so far into the radius to use next, aiming at miscoverage `alpha` (e.g. 0.1): one
instance per horizon step (pooled) or per track and horizon step (per track), always as
separate instances, since scores of different horizons have different scales.

Each online method is a pair of pure functions, like optax's `GradientTransformation`, with
one signature for all of them (`OnlineConformal`): `init(initial_radius=None, *, scores=None,
dtype=None) -> state` and `update(state, scores, mask=None, *, radius_in_force=None,
uniform=None) -> (state, radius)`, the state a NamedTuple of arrays that holds `radius`, the
radius in force until the next update. The keyword extras are the same for every method: one
that does not need an extra (DtACI judges no score against the radius in force; ACI and PID
draw nothing) accepts it and ignores it, so a caller never asks which method it holds. They
jit, vmap over any leading axes (tracks, horizon steps, environments) and scan over time:

    method = conformal.dtaci(alpha=0.1)              # or ONLINE_METHODS[name](alpha=0.1)
    state = jax.vmap(jax.vmap(method.init))(q0)                  # q0 (N, P): 0.1 * k metres
    feed = conformal.score_buffer_init(num_tracks=N, horizon=P)
    # per time step:
    feed, delayed = conformal.score_buffer_update(feed, predicted, valid, observed, detected)
    per_track = jax.vmap(jax.vmap(method.update))                  # batch of 1 score each
    state, radius = per_track(state, delayed.scores[..., None], delayed.mask[..., None],
                              radius_in_force=delayed.issued[..., None],
                              uniform=jax.random.uniform(key, (N, P)))   # radius (N, P)
    feed = conformal.record_issued(feed, radius)                  # back with its scores

    pooled = jax.vmap(method.update)                               # one instance per horizon
    state, radius = pooled(state, delayed.scores.T, delayed.mask.T,
                           radius_in_force=delayed.issued.T, uniform=uniforms_p)    # (P,)

`Regions` does exactly this for a stream's track slots, pooled or per track, and
`simultaneous` gives whole-path discs instead. Offline, from calibration paths' scores
(paths, P), `whole_path_region` gives radii (P,) that hold every step of a new exchangeable
path together with probability at least 1 - alpha, and `joint_coverage` reports how many
test paths they held, with an exact binomial interval:

    region = conformal.whole_path_region(scores, mask, alpha=0.1, fit=first_half)
    inside = conformal.paths_inside(test_scores, test_mask, region.radii)
    report = conformal.joint_coverage(inside, test_mask.any(axis=-1))  # .lower, .upper

**Pooled vs per track.** Per track: an instance per (track, horizon step) learns that
person's radius from that person's scores alone (GenSafeNav's ROS 2 node; a new person starts
from scratch). Pooled: an instance per horizon step gets, at each time step, the batch of
scores of every detected track (at most one per track; `mask` marks those present), and gives
one radius to everyone. A masked entry changes nothing; an update whose entries are all
masked leaves the state as it was (but for ACI's `initial_radius`, in force until its first
update, which replaces it with its window's quantile).

The methods, one module each under `gst_jax/conformal/_src/`, whose docstring gives the
method's equations and guarantees, and what runs them:

- `split_radius` (`split.py`): split conformal, a radius fixed from calibration scores;
- `aci` (`aci.py`): adaptive conformal inference (Gibbs & Candès 2021);
- `dtaci` (`dtaci.py`): DtACI's experts (Gibbs & Candès 2022), as GenSafeNav runs it;
- `pid` (`pid.py`): conformal PID control's quantile tracking and integrator (Angelopoulos,
  Candès & Tibshirani 2023);
- `score_buffer_init`, `score_buffer_update`, `record_issued`, `reset_slots` (`delayed.py`):
  the delayed scores of a stream of predictions and observations;
- `Regions`, `ONLINE_METHODS` (`regions.py`): the per-step discs of a stream's track slots,
  one instance per horizon step (pooled) or per slot and horizon step, the method by name
  (what `gst_jax.stream` and `gst_jax.coverage` run);
- `simultaneous`, `path_errors`, `path_scales` (`paths.py`): whole-path discs, one score per
  prediction (the largest of its steps' errors over their scales), so that all P steps of a
  prediction hold together;
- `whole_path_region`, `PathRegion`, `path_scores`, `step_quantiles`, `paths_inside`,
  `joint_coverage`, `JointCoverage` (`whole_path.py`): whole-path regions calibrated across
  trajectories (Cleaveland, Lee, Pappas & Lindemann 2024: per-step scales from one split, a
  split-conformal quantile of the normalised max on the other), P(every step of a new
  exchangeable path inside) in [1 - alpha, 1 - alpha + 1/(n+1)), and the joint coverage of
  test paths as a count with its exact binomial interval;
- `clopper_pearson` (`binomial.py`): the exact (Clopper-Pearson) binomial interval, from the
  regularised incomplete beta in float64, no scipy.

The plain-numpy references of the update equations are in gst_jax/testing/
conformal_reference.py; tests/test_conformal.py and tests/test_whole_path.py check these
functions against them.
"""

from gst_jax.conformal._src.aci import ACIState, aci
from gst_jax.conformal._src.base import BATCH_MODES, LOSSES, OUTPUTS, OnlineConformal
from gst_jax.conformal._src.binomial import clopper_pearson
from gst_jax.conformal._src.delayed import (
    DelayedScores,
    ScoreBufferState,
    record_issued,
    reset_slots,
    score_buffer_init,
    score_buffer_update,
)
from gst_jax.conformal._src.dtaci import DtACIState, dtaci
from gst_jax.conformal._src.paths import path_errors, path_scales, simultaneous
from gst_jax.conformal._src.pid import PIDState, pid
from gst_jax.conformal._src.regions import ONLINE_METHODS, Regions
from gst_jax.conformal._src.split import split_radius
from gst_jax.conformal._src.whole_path import (
    JointCoverage,
    PathRegion,
    joint_coverage,
    path_scores,
    paths_inside,
    step_quantiles,
    whole_path_region,
)

__all__ = ["ACIState", "BATCH_MODES", "DelayedScores", "DtACIState", "JointCoverage", "LOSSES",
           "ONLINE_METHODS", "OUTPUTS", "OnlineConformal", "PIDState", "PathRegion", "Regions",
           "ScoreBufferState", "aci", "clopper_pearson", "dtaci", "joint_coverage", "path_errors",
           "path_scales", "path_scores", "paths_inside", "pid", "record_issued", "reset_slots",
           "score_buffer_init", "score_buffer_update", "simultaneous", "split_radius",
           "step_quantiles", "whole_path_region"]
