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
    """An online conformal method: `init(...) -> state`, `update(state, scores, mask, ...) ->
    (state, radius)`; both pure, for one instance (vmap for more)."""

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
