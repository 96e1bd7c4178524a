"""Sweep members: configurations (n, detection, seed) trained side by side as stacked pytrees.

Every member shares one parameter layout: head slots G sized so that every member's n
divides G. n, the ghost switch and the "F" switch are per-member traced values.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Sequence

import jax
import jax.numpy as jnp

from gst_jax.config import DETECTION, Member, ModelConfig


def plan_members(edge_heads: Sequence[int], detection: str, seeds: Sequence[int]) -> list[Member]:
    """Every (n, detection, seed) combination, in a fixed order."""
    return [Member(n, fd, seed) for n in edge_heads for fd in DETECTION[detection]
            for seed in seeds]


def sweep_model_config(base: ModelConfig, members: Sequence[Member]) -> ModelConfig:
    """The shared layout: head slots G = lcm of the sparse n, so every member's n divides G."""
    slots = math.lcm(*[max(m.edge_heads, 1) for m in members])
    return dataclasses.replace(base, max_edge_heads=slots, num_edge_heads=members[0].edge_heads)


def member_config(config: ModelConfig, member: Member) -> ModelConfig:
    """The single-run config of a member: its n, the sweep's head slots."""
    return dataclasses.replace(config, num_edge_heads=member.edge_heads)


def stack(trees: Sequence[Any]) -> Any:
    """Stack pytrees of equal structure along a new leading member axis."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *trees)


def unstack(tree: Any, index: int) -> Any:
    """Member `index` of a stacked pytree."""
    return jax.tree.map(lambda leaf: leaf[index], tree)


def stacked_shape(tree: Any, num_members: int) -> Any:
    """The abstract (shape and dtype) tree of `num_members` stacked copies of `tree`."""
    return jax.tree.map(lambda leaf: jax.ShapeDtypeStruct((num_members,) + tuple(leaf.shape),
                                                          leaf.dtype), tree)
