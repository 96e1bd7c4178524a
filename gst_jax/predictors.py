"""What a stream or a simulated robot predicts with: one protocol, chosen by object.

    predictor.predict(params, key, positions, detected, truth=None)
        -> futures (K, P, C, 2), predicted (C,)

from every slot's last T observed positions (C, T, 2) and detections (C, T); predicted marks
the slots whose futures mean something. The predictors:

- `GST(config, ...)`: a gst_jax model (or CrowdNav++'s, `convention="crowdnav"`), its weights
  in `params`;
- `ConstantVelocity`: each track's last displacement repeated (the baseline to beat);
- `Standing`: everyone stays where they are (a planner without a predictor);
- `Truth`: the simulator's own futures, which only a simulator can give (`truth`, a function
  of nothing that returns them (C, P, 2)): the upper bound on any predictor.

A predictor is a frozen dataclass (hashable: jit's static argument, one compiled program per
predictor); `uses_key` says whether it draws random numbers (the callers split a key only for
those, so that adding a predictor changes no other's draws).
"""

from __future__ import annotations

import dataclasses
from typing import Callable, ClassVar, Protocol

import jax
import jax.numpy as jnp

from gst_jax import crowdnav
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch, node_mask_from_positions
from gst_jax.errors import DataError
from gst_jax.model import Params
from gst_jax.predict import make_predict

# The simulator's futures (C, P, 2), computed only where a predictor asks for them.
TruthFn = Callable[[], jax.Array]


class Predictor(Protocol):
    """Futures of every slot from its history (module docstring)."""

    uses_key: ClassVar[bool]

    @property
    def obs_len(self) -> int: ...

    @property
    def pred_len(self) -> int: ...

    def predict(self, params: Params | None, key: jax.Array | None, positions: jax.Array,
                detected: jax.Array, truth: TruthFn | None = None
                ) -> tuple[jax.Array, jax.Array]: ...


def last_two_detected(detected: jax.Array) -> jax.Array:
    """(C,) the slots detected at both of the last two steps: those a displacement exists
    for."""
    return (detected[:, -2:] > 0).all(axis=-1)


@dataclasses.dataclass(frozen=True)
class GST:
    """A gst_jax model: config, the model's; num_samples: K futures per track (1 with `mean`);
    mean: every predicted step the mean of the output head (GST (P)'s Gaussian; GST (D) is its
    mean anyway), the graph still sampled where the model selects edges; convention: "gst"
    (the model reads undetected steps as gst_jax's windows hold them) or "crowdnav"
    (CrowdNav++'s predictor: -999 and its displacement mask, `gst_jax.crowdnav.predict`; mean
    mode)."""

    config: ModelConfig
    num_samples: int = 1
    mean: bool = True
    convention: str = "gst"
    uses_key: ClassVar[bool] = True

    def __post_init__(self):
        if self.convention not in ("gst", "crowdnav"):
            raise DataError(f"convention must be 'gst' or 'crowdnav', got {self.convention!r}")
        if self.convention == "crowdnav" and (self.num_samples != 1 or not self.mean):
            raise DataError("CrowdNav++'s predictor predicts the mean only (num_samples=1, "
                            "mean=True)")

    @property
    def obs_len(self) -> int:
        return self.config.obs_len

    @property
    def pred_len(self) -> int:
        return self.config.pred_len

    def predict(self, params: Params | None, key: jax.Array | None, positions: jax.Array,
                detected: jax.Array, truth: TruthFn | None = None
                ) -> tuple[jax.Array, jax.Array]:
        assert params is not None and key is not None, "GST predicts with its parameters and a key"
        if self.convention == "crowdnav":
            traj = jnp.where(detected[..., None] > 0, positions, crowdnav.MISSING)
            output, predicted = crowdnav.predict(params, self.config, traj[None],
                                                 detected[None, ..., None])
            return jnp.swapaxes(output[0, ..., :2], 0, 1)[None], predicted[0, :, 0]
        prediction = make_predict(self.config, self.num_samples, with_graph=False,
                                  mean=self.mean)(params, key, as_batch(positions, detected))
        return prediction.positions[:, 0], prediction.predicted_mask[0]


def as_batch(positions: jax.Array, detected: jax.Array) -> SceneBatch:
    """Slots' histories (C, T, 2), (C, T) as a one-scene batch of the model's."""
    position_mask = jnp.swapaxes(detected, 0, 1)[None]                          # (1, T, C)
    return SceneBatch(positions=jnp.swapaxes(positions, 0, 1)[None],
                      position_mask=position_mask,
                      node_mask=node_mask_from_positions(position_mask),
                      scene_mask=jnp.ones(1), window_index=jnp.zeros(1, jnp.int32))


@dataclasses.dataclass(frozen=True)
class _FromHistory:
    """A predictor that reads only the histories: its grid, and no random draws."""

    obs_len: int = 5
    pred_len: int = 5
    uses_key: ClassVar[bool] = False


@dataclasses.dataclass(frozen=True)
class ConstantVelocity(_FromHistory):
    """Each track's last displacement repeated over the horizon."""

    def predict(self, params: Params | None, key: jax.Array | None, positions: jax.Array,
                detected: jax.Array, truth: TruthFn | None = None
                ) -> tuple[jax.Array, jax.Array]:
        now, last = positions[:, -1], positions[:, -1] - positions[:, -2]
        steps = jnp.arange(1, self.pred_len + 1)[:, None, None]
        return (now[None] + steps * last[None])[None], last_two_detected(detected)


@dataclasses.dataclass(frozen=True)
class Standing(_FromHistory):
    """Everyone stays where they are: a planner without a predictor."""

    def predict(self, params: Params | None, key: jax.Array | None, positions: jax.Array,
                detected: jax.Array, truth: TruthFn | None = None
                ) -> tuple[jax.Array, jax.Array]:
        futures = jnp.broadcast_to(positions[None, None, :, -1],
                                   (1, self.pred_len, *positions[:, -1].shape))
        return futures, last_two_detected(detected)


@dataclasses.dataclass(frozen=True)
class Truth(_FromHistory):
    """The simulator's own futures (`truth`): what no predictor can beat."""

    def predict(self, params: Params | None, key: jax.Array | None, positions: jax.Array,
                detected: jax.Array, truth: TruthFn | None = None
                ) -> tuple[jax.Array, jax.Array]:
        if truth is None:
            raise ValueError("Truth predicts only inside a simulator, which gives `truth`")
        return jnp.swapaxes(truth(), 0, 1)[None], last_two_detected(detected)
