"""`SceneBatch`: the padded, masked arrays that every jitted function consumes.

Built by numpy code (this package never imports jax); `gst_jax.graph` registers it as a jax
pytree so it can be passed straight into `jit`, `vmap` and `scan`.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class SceneBatch:
    """B scene windows of T steps with up to N pedestrians each, padded and masked.

    Attributes:
      positions: (B, T, N, 2) float32 metres; zero where a pedestrian was not detected.
      position_mask: (B, T, N) float32, 1 where the position exists.
      node_mask: (B, T, N) float32, MODEL.md's m: at t = 0 the position mask, at t > 0 the
        product of the position masks at t - 1 and t (a displacement exists).
      scene_mask: (B,) float32, 1 for real windows, 0 for padding windows.
      window_index: (B,) int32, index of each window in its dataset split (-1 for padding).
    """

    positions: np.ndarray
    position_mask: np.ndarray
    node_mask: np.ndarray
    scene_mask: np.ndarray
    window_index: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        """(B, T, N)."""
        return tuple(self.position_mask.shape)


DATA_FIELDS = tuple(f.name for f in dataclasses.fields(SceneBatch))


def node_mask_from_positions(position_mask: np.ndarray) -> np.ndarray:
    """MODEL.md 1.6: m^0 = valid^0, m^t = valid^{t-1} * valid^t.  (..., T, N) -> (..., T, N)."""
    node_mask = position_mask.copy()
    node_mask[..., 1:, :] = position_mask[..., 1:, :] * position_mask[..., :-1, :]
    return node_mask
