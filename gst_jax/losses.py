"""The training loss of a rollout, per scene as in the release (docs/MODEL.md 3): the output
head's (`gst_jax.model.heads`) on the predicted steps."""

from __future__ import annotations

import jax

from gst_jax import graph
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.model.heads import Losses, head
from gst_jax.rollout import RolloutOutput


def scene_losses(config: ModelConfig, output: RolloutOutput, batch: SceneBatch,
                 score_partial: jax.Array | bool = False) -> jax.Array:
    """Per-scene training loss (B,) of the configured output head; score_partial: GST (P)'s
    also of the partially detected (`TrainConfig.score_partial`; may be traced)."""
    obs_len = config.obs_len
    return head(config.output).scene_loss(Losses(
        displacements=output.displacements, mu=output.mu, sigma=output.sigma, corr=output.corr,
        true_displacements=graph.displacements(batch.positions, batch.node_mask)[:, obs_len:],
        step_mask=output.predicted_mask[:, None, :] * batch.node_mask[:, obs_len:],
        fully_detected=batch.fully_detected_mask, score_partial=score_partial))
