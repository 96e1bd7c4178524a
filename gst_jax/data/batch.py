"""`SceneBatch`: the padded, masked arrays that every jitted function consumes.

Built by numpy code (this package never imports jax). A NamedTuple, so it is a jax pytree
by itself (as jraph's `GraphsTuple`) and passes straight into `jit`, `vmap` and `scan`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


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

    positions: np.ndarray
    position_mask: np.ndarray
    node_mask: np.ndarray
    scene_mask: np.ndarray
    window_index: np.ndarray
    predicted_slots: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """(B, T, N)."""
        return tuple(self.position_mask.shape)


def node_mask_from_positions(position_mask: np.ndarray) -> np.ndarray:
    """docs/MODEL.md 1.6: m^0 = valid^0, m^t = valid^{t-1} valid^t.  (..., T, N) -> (..., T, N)."""
    node_mask = position_mask.copy()
    node_mask[..., 1:, :] = position_mask[..., 1:, :] * position_mask[..., :-1, :]
    return node_mask
