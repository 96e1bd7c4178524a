"""Whole-path regions: discs that hold every predicted step of a prediction together.

Per-step discs at alpha do not hold a whole path (the union of the P steps' misses is larger
than any one of them). `simultaneous` gives each prediction one score, m = max_k e_k / scale_k
over its P steps (e_k its horizon-k distance), known once its last step is observed, P frames
after it was made, and runs an online method on those scores: the prediction of frame t0
gets radii q(t0) scale_k (metres, (P,)), and all P steps are inside exactly when m <= q(t0),
so the method's own coverage guarantee is one on the whole path. `path_errors` reads a
prediction's errors out of the delayed scores, `path_scales` makes the scales.
"""

from __future__ import annotations

from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.conformal._src.base import OnlineConformal


def path_errors(scores: np.ndarray, masks: np.ndarray, made: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """The horizon-k errors (P, C) of the predictions made at frame `made` (they come back k
    frames later) and which of them were observed at every step (C,); scores and masks
    (F, C, P): the delayed scores of each frame (`DelayedScores`)."""
    steps = np.arange(scores.shape[-1])
    return (scores[made + 1 + steps, :, steps],
            np.asarray(masks[made + 1 + steps, :, steps].all(axis=0)))


def path_scales(errors: np.ndarray) -> np.ndarray:
    """Per horizon step k, the mean of the errors (n, P), from a prior of one error of 0.1 k m."""
    steps = np.arange(errors.shape[-1])
    return (errors.sum(axis=0) + 0.1 * (steps + 1)) / (len(errors) + 1)


def simultaneous(method: OnlineConformal, streams: Sequence[tuple[np.ndarray, np.ndarray]],
                 calibrating: int, key: jax.Array) -> dict:
    """Whole-path discs from one score per prediction (this module's docstring), calibrated,
    then adapted online, over streams of delayed scores (scores, masks), each (F, C, P), one
    after another.

    The first `calibrating` frames (counted over the streams in order) fix the scales
    (`path_scales` of the errors of the predictions completed during them) and start
    `method` (an `OnlineConformal`, pooled over the tracks) from their scores m:
    `init(scores=...)` (ACI's window holds them; DtACI and PID start at their split-conformal
    radius or, where they are too few for the level, at their largest, at least 1: a radius
    they can move from). After them the method turns each returned m into q, each judged
    against the q issued with its prediction (a method that draws takes one uniform per frame
    from `key`, split per stream). The scales and the method carry over from one stream to
    the next. Predictions with a step unobserved are neither scored nor counted, nor are
    those made during the calibration frames.

    Returns, over the predictions made after the calibration frames: `joint_coverage` (the
    fraction with every step inside; NaN for none), `joint_predictions` (how many), and per
    step the coverage and the mean radius (`coverage`, `radius`, (P,) lists).

    Why calibrated: scores formed with the scales of their own moment (running means) are not
    comparable across the stream, and a method started from nothing spends a short stream's
    first frames with infinite or far too small radii, then compensates; either way the
    predictions after calibration came out 0.02-0.08 below 0.9 on four of five scenes."""
    update = jax.jit(method.update)
    horizon = streams[0][0].shape[-1] if streams else 0
    state, scale = None, None
    calibration: list[np.ndarray] = []
    inside_all, inside, radii, first = [], [], [], 0
    keys = jax.random.split(key, max(len(streams), 1))
    for (scores, masks), key in zip(streams, keys):
        frames = scores.shape[0]
        issued = np.full(frames, np.nan)                  # NaN: made during the calibration
        uniforms = np.asarray(jax.random.uniform(key, (frames,)))
        for t in range(frames):
            if state is None and first + t >= calibrating:
                errors = np.concatenate(calibration or [np.zeros((0, horizon))])  # (n, P)
                scale = path_scales(errors)
                ratios = np.max(errors / scale, axis=1)
                state = method.init(float(np.max(ratios, initial=1.0)),
                                    scores=jnp.asarray(ratios))
            made = t - horizon                          # the predictions completed now
            if made >= 0:
                errors, scored = path_errors(scores, masks, made)               # (P, C), (C,)
                if state is None:
                    calibration.append(errors[:, scored].T)
                elif not np.isnan(issued[made]):
                    assert scale is not None, "set with the state"
                    ratio = np.max(errors / scale[:, None], axis=0)
                    state = update(state, ratio, scored,
                                   radius_in_force=np.full(ratio.shape, issued[made]),
                                   uniform=uniforms[t])[0]
                    inside_all += (ratio <= issued[made])[scored].tolist()
                    given = issued[made] * scale                                # (P,)
                    inside += (errors <= given[:, None]).T[scored].tolist()
                    radii += [given] * int(scored.sum())
            if state is not None:
                issued[t] = float(state.radius)
        first += frames
    per_step = np.asarray(inside).reshape(-1, horizon)
    step_radii = np.asarray(radii).reshape(-1, horizon)
    return {"joint_coverage": float(np.mean(inside_all)) if inside_all else float("nan"),
            "joint_predictions": len(inside_all), "coverage": per_step.mean(axis=0).tolist(),
            "radius": step_radii.mean(axis=0).tolist()}
