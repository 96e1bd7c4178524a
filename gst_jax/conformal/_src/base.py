"""What every online method shares: the pair of pure functions and the checks of its inputs."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp

LOSSES = ("consistent", "gensafenav")
OUTPUTS = ("sample", "mean")
BATCH_MODES = ("sequential", "mean")


@dataclasses.dataclass(frozen=True)
class OnlineConformal:
    """An online conformal method, a pair of pure functions for one instance (vmap for
    more), the same signature for every method:

    init(initial_radius=None, *, scores=None, dtype=None) -> state: the radius in force
      before the first update (None: the method's own start), or calibration scores (n,)
      to start from.
    update(state, scores (B,), mask (B,) = None, *, radius_in_force=None, uniform=None) ->
      (state, radius): the scores that came back, each judged against `radius_in_force`
      (the radius issued with its prediction; `state.radius` for None), `uniform` a draw in
      [0, 1) for a method that draws (DtACI's expert); `state.radius` is the radius returned.

    An extra a method does not need it accepts and ignores, so that a caller passes the same
    arguments whatever the method."""

    init: Callable[..., Any]
    update: Callable[..., tuple[Any, jax.Array]]


def scores_and_mask(scores, mask, dtype) -> tuple[jax.Array, jax.Array]:
    scores = jnp.asarray(scores, dtype)
    if scores.ndim != 1:
        raise ValueError(f"scores must be a batch (B,) for one instance, got shape "
                         f"{scores.shape}; vmap over tracks or horizon steps")
    mask = jnp.ones(scores.shape, bool) if mask is None else jnp.asarray(mask, bool)
    if mask.shape != scores.shape:
        raise ValueError(f"mask {mask.shape} must have the shape of scores {scores.shape}")
    return scores, mask


def check_alpha(alpha) -> None:
    """Refuse a target miscoverage outside (0, 1) (NaN included); a traced one is the
    caller's to check."""
    try:
        value = float(alpha)
    except TypeError:                     # a tracer or an array of several
        return
    if not 0 < value < 1:
        raise ValueError(f"alpha must lie strictly between 0 and 1, got {alpha}")
