"""Predictions that adapt online to a crowd that changes, from the delayed ground truth.

A prediction of horizon k made at step t is scored once step t + k is observed. Where the
crowd changes (it speeds up, or switches motion model), those scores show how the
predictor is wrong before anything else does. Each method here learns a correction of the
predicted displacements from them, pooled over everyone in view, and applies it to the next
predictions:

- `SpeedScale`: the crowd's speed relative to the predictor's, one number (physical: a
  crowd 1.5x faster walks 1.5x as far along the predicted paths): the displacement
  predicted from a person's position now, times s. s is the forgetting least-squares fit of
  observed against predicted displacements, bounded, starting at 1.
- `RLSBlend`: per horizon step k, the predicted displacement d_k and constant velocity's
  k v (v the last observed step) weighed, a_k d_k + b_k k v, by recursive least squares with
  forgetting (a Bayesian linear last layer on the predictor's output; its prior is the
  predictor itself, a = 1, b = 0): it can learn to trust the model less, or more, and to
  move faster, per horizon.

Like `gst_jax.conformal`'s methods, each is a frozen dataclass of pure methods with its state
a pytree of arrays, for N person slots and horizon P (jit, vmap over environments, scan over
time):

    method = adaptation.SpeedScale()
    state = method.init(num_slots=N, horizon=P)
    # per step: what was observed now, then the new predictions
    state = method.observe(state, positions, detected)         # (N, 2), (N,)
    adapted = method.apply(state, positions, predicted, last_step)   # (N, P, 2)
    state = method.issue(state, positions, predicted, last_step, valid)

`observe` scores the predictions made 1..P steps ago against `positions`; `issue` keeps the
raw predictions (before adaptation: the correction is of the predictor, not of itself).
`reset_slots` forgets the issued predictions of slots that now hold someone else. Forgetting
(`forgetting` per step) lets the correction follow a crowd that changes again.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Protocol

import jax
import jax.numpy as jnp


class Issued(NamedTuple):
    """The last P steps' raw predictions, newest last: displacements from the position at
    issue (P, N, P, 2), constant velocity's (P, N, P, 2), positions at issue (P, N, 2) and
    whether each slot was predicted (P, N)."""

    predicted: jax.Array
    constant_velocity: jax.Array
    anchors: jax.Array
    valid: jax.Array


class AdaptationState(NamedTuple):
    """The issued predictions and the method's statistics (`stats`)."""

    issued: Issued
    stats: tuple


class Adaptation(Protocol):
    """An online correction (module docstring): a frozen dataclass (hashable, so that it is
    a static argument of the programs that use it) with these pure methods."""

    def __hash__(self) -> int: ...

    def init(self, num_slots: int, horizon: int) -> AdaptationState: ...

    def observe(self, state: AdaptationState, positions: jax.Array, detected: jax.Array
                ) -> AdaptationState: ...

    def apply(self, state: AdaptationState, positions: jax.Array, predicted: jax.Array,
              last_step: jax.Array) -> jax.Array: ...

    def issue(self, state: AdaptationState, positions: jax.Array, predicted: jax.Array,
              last_step: jax.Array, valid: jax.Array) -> AdaptationState: ...

    def reset_slots(self, state: AdaptationState, which: jax.Array) -> AdaptationState: ...


class _Issues:
    """What every method shares: keeping the raw predictions, forgetting slots."""

    def issue(self, state: AdaptationState, positions: jax.Array, predicted: jax.Array,
              last_step: jax.Array, valid: jax.Array) -> AdaptationState:
        """Keep this step's raw predictions (N, P, 2) of the slots `valid` (N,), made from
        `positions` (N, 2) with last observed steps `last_step` (N, 2)."""
        horizon = predicted.shape[1]
        steps = jnp.arange(1, horizon + 1)[None, :, None]
        # A slot not predicted may hold NaN (gst_jax's models mark "nobody" so), and a mask's
        # 0 times NaN is NaN: such slots are kept as zeros.
        keep = valid[:, None, None]
        new = Issued(jnp.where(keep, predicted - positions[:, None], 0.0),
                     jnp.where(keep, steps * last_step[:, None], 0.0),
                     jnp.where(valid[:, None], positions, 0.0), valid)
        issued = jax.tree.map(lambda ring, one: jnp.concatenate([ring[1:], one[None]]),
                              state.issued, new)
        return state._replace(issued=issued)

    def reset_slots(self, state: AdaptationState, which: jax.Array) -> AdaptationState:
        """Forget the issued predictions of the slots `which` (N,): someone else is there."""
        return state._replace(issued=state.issued._replace(
            valid=state.issued.valid & ~which[None]))


def _matured(issued: Issued, positions: jax.Array, detected: jax.Array):
    """The predictions whose step is now, from each of the last P issues: the one made k
    steps ago at its horizon k. Returns predicted, constant-velocity and observed
    displacements (P, N, 2) and their mask (P, N), row k - 1 for horizon k."""
    horizon = issued.anchors.shape[0]
    k = jnp.arange(1, horizon + 1)
    row = horizon - k                                     # issued k steps ago
    predicted = issued.predicted[row, :, k - 1]           # (P, N, 2)
    constant_velocity = issued.constant_velocity[row, :, k - 1]
    mask = issued.valid[row] & detected[None]
    observed = jnp.where(mask[..., None], positions[None] - issued.anchors[row], 0.0)
    return predicted, constant_velocity, observed, mask


def _empty(num_slots: int, horizon: int) -> Issued:
    zeros = jnp.zeros((horizon, num_slots, horizon, 2))
    return Issued(zeros, zeros, jnp.zeros((horizon, num_slots, 2)),
                  jnp.zeros((horizon, num_slots), bool))


@dataclasses.dataclass(frozen=True)
class SpeedScale(_Issues):
    """The crowd's speed relative to the predictor's, s: every predicted displacement times
    s. s = (w + sum l^age o.d) / (w + sum l^age |d|^2) over matured predictions d and their
    observed displacements o (l: `forgetting` per step, 0.8: a memory of about 5 steps; w:
    `prior_weight`, in m^2, holding s at 1 until enough is seen), clipped to `bounds`."""

    forgetting: float = 0.8
    prior_weight: float = 1.0
    bounds: tuple[float, float] = (0.5, 2.0)

    def init(self, num_slots: int, horizon: int) -> AdaptationState:
        w = jnp.asarray(self.prior_weight, jnp.float32)
        return AdaptationState(_empty(num_slots, horizon), (w, w))

    def observe(self, state, positions, detected):
        predicted, _, observed, mask = _matured(state.issued, positions, detected)
        numerator, denominator = state.stats
        weight, w, keep = mask[..., None], self.prior_weight, self.forgetting
        numerator = keep * (numerator - w) + w + jnp.sum(weight * observed * predicted)
        denominator = keep * (denominator - w) + w + jnp.sum(weight * predicted ** 2)
        return state._replace(stats=(numerator, denominator))

    def scale(self, state: AdaptationState) -> jax.Array:
        numerator, denominator = state.stats
        return jnp.clip(numerator / denominator, *self.bounds)

    def apply(self, state, positions, predicted, last_step):
        return positions[:, None] + self.scale(state) * (predicted - positions[:, None])


@dataclasses.dataclass(frozen=True)
class RLSBlend(_Issues):
    """Per horizon step k, a_k d_k + b_k k v (d_k the predicted displacement, v the last
    observed step): (a_k, b_k) by recursive least squares with forgetting `forgetting` per
    step, both components of every matured prediction an equation, the prior (1, 0) held with
    `prior_weight` (m^2): the information R_k (2, 2) and r_k (2,) decay towards the prior's."""

    forgetting: float = 0.9
    prior_weight: float = 1.0

    def _prior(self):
        return (self.prior_weight * jnp.eye(2, dtype=jnp.float32),
                self.prior_weight * jnp.array([1.0, 0.0], jnp.float32))

    def init(self, num_slots: int, horizon: int) -> AdaptationState:
        information, target = self._prior()
        return AdaptationState(_empty(num_slots, horizon),
                               (jnp.broadcast_to(information, (horizon, 2, 2)),
                                jnp.broadcast_to(target, (horizon, 2))))

    def observe(self, state, positions, detected):
        predicted, constant_velocity, observed, mask = _matured(state.issued, positions,
                                                                detected)
        features = jnp.stack([predicted, constant_velocity], axis=-1)     # (P, N, 2, 2)
        features = features * mask[..., None, None]
        information, target = state.stats
        prior_information, prior_target = self._prior()
        keep = self.forgetting
        information = (keep * (information - prior_information) + prior_information
                       + jnp.einsum("pncf,pncg->pfg", features, features))
        target = (keep * (target - prior_target) + prior_target
                  + jnp.einsum("pncf,pnc->pf", features, observed))
        return state._replace(stats=(information, target))

    def weights(self, state: AdaptationState) -> jax.Array:
        """(P, 2): each horizon's weight of the model's displacement and of CV's."""
        information, target = state.stats
        return jnp.linalg.solve(information, target[..., None])[..., 0]

    def apply(self, state, positions, predicted, last_step):
        w = self.weights(state)
        steps = jnp.arange(1, predicted.shape[1] + 1)[None, :, None]
        displacement = predicted - positions[:, None]
        return positions[:, None] + (w[None, :, :1] * displacement
                                     + w[None, :, 1:] * steps * last_step[:, None])


# The methods by the name commands and records give them.
METHODS = {"speed-scale": SpeedScale, "rls-blend": RLSBlend}
