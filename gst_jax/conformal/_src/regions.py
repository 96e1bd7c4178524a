"""Per-step regions of a stream: a disc around every predicted step of every track slot.

`Regions` names an online method (by `ONLINE_METHODS`), its target miscoverage and how its
instances are laid out: one per horizon step, fed every track's score (pooled), or one per
track slot and horizon step, fed that track's alone (per track). `init` gives the fresh
states, `advance` takes the delayed scores of one time step (`DelayedScores`, (C, P)) and
gives the radii (C, P) to issue with the predictions made then. Every method is called the
same way (`OnlineConformal`); the stream (`gst_jax.stream`) keeps the states beside its score
buffer, and `gst_jax.coverage` replays them over a recording.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Callable

import jax
import jax.numpy as jnp

from gst_jax.conformal._src.aci import aci
from gst_jax.conformal._src.base import OnlineConformal
from gst_jax.conformal._src.delayed import DelayedScores
from gst_jax.conformal._src.dtaci import dtaci
from gst_jax.conformal._src.pid import pid
from gst_jax.errors import DataError

# The online methods by name: each `name(alpha, **options) -> OnlineConformal`.
ONLINE_METHODS: dict[str, Callable[..., OnlineConformal]] = {"aci": aci, "dtaci": dtaci,
                                                             "pid": pid}


@dataclasses.dataclass(frozen=True)
class Regions:
    """Calibrated discs around every predicted step: each prediction is scored k steps later,
    at horizon k, by its distance to the position observed then, and an online method turns
    the scores into the next radii.

    method: "dtaci" (GenSafeNav's variant, consistent loss, drawn expert), "aci" (window of 1000
    scores), "pid" (quantile tracking and integrator), or None: score only, every radius
    infinite (split conformal is calibrated from those scores,
    `gst_jax.conformal.split_radius`). alpha: target miscoverage. pooled: one instance per
    horizon step, fed every track's score (default), or one per slot and horizon step, fed that
    track's alone (GenSafeNav's ROS 2 node; a new track starts from scratch). options: (name,
    value) pairs for the method's constructor, e.g. (("gamma", 0.002),) (`conformal.aci`,
    `conformal.dtaci`, `conformal.pid`). The scored prediction is the mean of the K samples.
    """

    method: str | None = "dtaci"
    alpha: float = 0.1
    pooled: bool = True
    options: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self):
        if self.method is not None and self.method not in ONLINE_METHODS:
            raise DataError(f"Regions: method must be one of "
                            f"{', '.join(map(repr, ONLINE_METHODS))} or None, got "
                            f"{self.method!r}")
        if not (isinstance(self.alpha, numbers.Real) and 0 < self.alpha < 1):
            raise DataError(f"Regions: alpha (the target miscoverage) must lie in (0, 1), got "
                            f"{self.alpha!r}")

    @property
    def online(self) -> OnlineConformal | None:
        if self.method is None:
            return None
        return ONLINE_METHODS[self.method](self.alpha, **dict(self.options))

    def init(self, capacity: int, horizon: int) -> Any:
        """Fresh states: (P,) pooled, (C, P) per track, each `init` with an initial radius of
        0.1 m per horizon step (where DtACI's experts and PID's tracking start; ACI's radius
        until its first update, which takes the quantile of its window instead)."""
        online = self.online
        if online is None:
            return None
        start = 0.1 * jnp.arange(1, horizon + 1, dtype=jnp.float32)              # (P,)
        if not self.pooled:
            start = jnp.broadcast_to(start, (capacity, horizon))
        init = online.init
        for _ in range(start.ndim):
            init = jax.vmap(init)
        return init(start)

    def advance(self, regions: Any, key: jax.Array, new_slots: jax.Array,
                delayed: DelayedScores) -> tuple[Any, jax.Array]:
        """The conformal state after the delayed scores (C, P) came back (per track, the
        `new_slots` (C,) start afresh first), and the radii (C, P) to issue now (infinite
        without a method). Each score is judged against the radius issued with it
        (`delayed.issued`); a method that draws takes its uniforms from `key`."""
        capacity, horizon = delayed.scores.shape
        if regions is None:
            return None, jnp.full((capacity, horizon), jnp.inf)
        if not self.pooled:                                     # a new track starts afresh
            fresh = self.init(capacity, horizon)
            regions = jax.tree.map(
                lambda new, old: jnp.where(new_slots.reshape((-1,) + (1,) * (old.ndim - 1)),
                                           new, old), fresh, regions)
        scores, mask, issued = delayed
        if self.pooled:                                         # per horizon: the tracks' batch
            scores, mask, issued = scores.T, mask.T, issued.T
        else:                                                   # per slot: a batch of one
            scores, mask, issued = scores[..., None], mask[..., None], issued[..., None]
        online = self.online
        assert online is not None, "a method's regions (None without one, returned above)"
        update = online.update
        for _ in range(regions.radius.ndim):
            update = jax.vmap(update)
        regions, radii = update(regions, scores, mask, radius_in_force=issued,
                                uniform=jax.random.uniform(key, regions.radius.shape))
        return regions, jnp.broadcast_to(radii, (capacity, horizon))
