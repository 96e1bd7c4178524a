"""`SceneBatch`: the padded, masked arrays that every jitted function consumes, and the masks
that say who is observed, predicted and scored (docs/MODEL.md 1.6-1.8, 2.3).

Built by numpy code (this package never imports jax). A NamedTuple, so it is a jax pytree
by itself (as jraph's `GraphsTuple`) and passes straight into `jit`, `vmap` and `scan`. The
mask functions take numpy or jax arrays alike (through the arrays' own namespace), so that
jitted code and the data layer read the same rule from one place.
"""

from __future__ import annotations

from typing import NamedTuple

from gst_jax.arrays import BatchArray


class SceneBatch(NamedTuple):
    """B scene windows of T steps with up to N pedestrians each, padded and masked.

    Attributes:
      positions: (B, T, N, 2) float32 metres; zero where a pedestrian was not detected.
      position_mask: (B, T, N) float32, 1 where the position exists.
      node_mask: (B, T, N) float32, the m of docs/MODEL.md 1.6: at t = 0 the position mask, at
        t > 0 the product of the position masks at t - 1 and t (a displacement exists).
      scene_mask: (B,) float32, 1 for real windows, 0 for padding windows.
      window_index: (B,) int32, index of each window in its dataset split (-1 for padding).
      predicted_slots: (B, P) float32 or None. The pedestrians that will be predicted
        (docs/MODEL.md 2.3: valid at the last observed step) sit in the first P slots, as
        windows order them, so the prediction steps compute on P of the N slots; this is
        their keep mask there, its width P a bucket size. None: any slot may be predicted.
    """

    positions: BatchArray
    position_mask: BatchArray
    node_mask: BatchArray
    scene_mask: BatchArray
    window_index: BatchArray
    predicted_slots: BatchArray | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """(B, T, N)."""
        return tuple(self.position_mask.shape)

    @property
    def fully_detected_mask(self):
        """(B, N) 1 for the pedestrians detected at every step: those scored."""
        return fully_detected(self.node_mask)

    def predicted_mask(self, obs_len: int):
        """(B, N) 1 for the pedestrians predicted (see `predicted`)."""
        return predicted(self.node_mask, obs_len)


def node_mask_from_positions(position_mask):
    """docs/MODEL.md 1.6: m^0 = valid^0, m^t = valid^{t-1} valid^t.  (..., T, N) -> (..., T, N)."""
    xp = position_mask.__array_namespace__()
    return xp.concat([position_mask[..., :1, :],
                      position_mask[..., 1:, :] * position_mask[..., :-1, :]], axis=-2)


def fully_detected(node_mask):
    """docs/MODEL.md 1.8: 1 for pedestrians valid at every step.  (..., T, N) -> (..., N)."""
    return node_mask.min(axis=-2)


def predicted(node_mask, obs_len: int):
    """docs/MODEL.md 2.3: 1 for the pedestrians the model predicts, those valid at the last
    observed step (detected at both of the last two: their last displacement exists).
    (..., T, N) -> (..., N)."""
    return node_mask[..., obs_len - 1, :]
