"""A drop-in for CrowdNav++'s trajectory predictor: its `gst_updated` GST, in mean mode.

CrowdNav++ (github.com/Shuijing725/CrowdNav_Prediction_AttnGraph) calls
`CrowdNavPredInterfaceMultiEnv.forward(input_traj, input_mask)` at every simulator step, for
all its environments at once. This module loads the same checkpoints and answers the same
call with the same numbers (docs/MODEL.md 6):

    predictor = gst_jax.crowdnav.load("gst_updated/results/<run>/sj")   # reading .pt needs torch
    output_traj, output_mask = predictor(input_traj, input_mask)

input_traj (n_env, N, obs_len, 2) positions, -999 where a human is not detected;
input_mask (n_env, N, obs_len, 1) 1 where detected. output_traj (n_env, N, pred_len, 5):
per predicted step the absolute mean position, then the standard deviations and the
correlation of the position accumulated over the steps; -999 positions for the humans not
predicted. output_mask (n_env, N, 1): 1 for the humans predicted. Its quirks are kept: a
displacement counts from step t - 1 to t where the human is detected at t - 1 and at the last
observed step (CrowdNav++ builds the mask so, not from t), and the accumulated Gaussian of a
human not predicted is that of a zero state, not masked.

The call is jitted once per input shape; underneath it is `predict(params, config,
input_traj, input_mask)`, a pure function that can be vmapped or called inside a jitted
planner. gst_jax serves CrowdNav++'s configuration: full connection (no edge selector), any
encoder depth and width, `lstm` or `faster_lstm`; its edge selector for n > 0 is another
design than the paper's and is refused.
"""

from __future__ import annotations

import dataclasses
import functools
import pickle
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import EVAL_TAU, ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.interop import load_state_dict, params_from_torch
from gst_jax.model import Controls
from gst_jax.rollout import rollout

MISSING = -999.0
# CrowdNav++'s simulator step: gst_updated's args do not record it.
CROWDNAV_STEP_S = 0.25


def model_config(args: Mapping[str, Any], step_s: float = CROWDNAV_STEP_S) -> ModelConfig:
    """The ModelConfig of a gst_updated run: `vars(args)` of its `checkpoint/args.pickle`."""
    unsupported = {"spatial": "gumbel_social_transformer", "decode_style": "recursive",
                   "lstm_num_layers": 1, "motion_dim": 2, "output_dim": 5,
                   "only_observe_full_period": False, "spatial_num_heads_edges": 0}
    for name, expected in unsupported.items():
        if args.get(name, expected) != expected:
            raise ValueError(f"gst_updated run with {name}={args[name]!r}: gst_jax serves "
                             f"{name}={expected!r} (docs/MODEL.md 6)")
    if args["temporal"] not in ("lstm", "faster_lstm"):
        raise ValueError(f"gst_updated run with temporal={args['temporal']!r}: expected lstm "
                         "or faster_lstm")
    width = args["embedding_size"]
    return ModelConfig(
        node_dim=width, edge_dim=2 * width, num_edge_heads=0, max_edge_heads=0,
        ghost=bool(args["ghost"]), encoder_layers=args["spatial_num_layers"],
        encoder_heads=args["spatial_num_heads"], encoder_ff_dim=128,
        lstm_hidden=args["lstm_hidden_size"],
        output="deterministic" if args.get("deterministic") else "gaussian",
        temporal=args["temporal"], step_s=step_s, obs_len=args["obs_seq_len"],
        pred_len=args["pred_seq_len"])


def predict(params, config: ModelConfig, input_traj: jax.Array, input_mask: jax.Array
            ) -> tuple[jax.Array, jax.Array]:
    """`CrowdNavPredInterfaceMultiEnv.forward` as a pure function (see the module docstring).

    input_traj (E, N, T, 2), input_mask (E, N, T, 1) -> output_traj (E, N, P, 5), output_mask
    (E, N, 1). Mean mode: hard graphs at tau 0.03, each predicted step the Gaussian's mean.
    """
    positions = jnp.swapaxes(jnp.asarray(input_traj, jnp.float32), 1, 2)       # (E, T, N, 2)
    detected = jnp.swapaxes(jnp.asarray(input_mask, jnp.float32)[..., 0], 1, 2)  # (E, T, N)
    # CrowdNav++'s displacement mask: from t - 1 to t where detected at t - 1 and at the last
    # observed step. Its positions keep their -999, as CrowdNav++ computes with them.
    node_mask = jnp.concatenate([detected[:, :1], detected[:, :-1] * detected[:, -1:]], axis=1)
    num_env = positions.shape[0]
    batch = SceneBatch(positions=positions, position_mask=detected, node_mask=node_mask,
                       scene_mask=jnp.ones(num_env), window_index=jnp.arange(num_env))
    controls = Controls.make(EVAL_TAU, config.num_edge_heads, config.ghost)
    out = rollout(params, jax.random.key(0), batch, config, controls, hard=True,
                  deterministic=True, mean=True)
    predicted = batch.predicted_mask(config.obs_len)                             # (E, N)
    mean = jnp.cumsum(out.mu, axis=1) + positions[:, -1:]
    mean = jnp.where(predicted[:, None, :, None] > 0, mean, MISSING)
    # The position's Gaussian after k steps: variances and covariances of the steps summed.
    sx, sy = out.sigma[..., 0], out.sigma[..., 1]
    sx_total = jnp.sqrt(jnp.cumsum(sx ** 2, axis=1))
    sy_total = jnp.sqrt(jnp.cumsum(sy ** 2, axis=1))
    corr_total = jnp.cumsum(out.corr * sx * sy, axis=1) / (sx_total * sy_total)
    output_traj = jnp.concatenate([mean, jnp.stack([sx_total, sy_total, corr_total], -1)], -1)
    return jnp.swapaxes(output_traj, 1, 2), predicted[..., None]


@dataclasses.dataclass(frozen=True)
class Predictor:
    """A CrowdNav++ predictor: `predictor(input_traj, input_mask) -> (output_traj,
    output_mask)`, numpy or jax arrays in, jax arrays out, jitted once per input shape."""

    params: Any
    config: ModelConfig

    @functools.cached_property
    def _predict(self):
        return jax.jit(functools.partial(predict, config=self.config))

    def __call__(self, input_traj, input_mask) -> tuple[jax.Array, jax.Array]:
        input_traj, input_mask = np.asarray(input_traj), np.asarray(input_mask)
        if input_traj.ndim != 4 or input_traj.shape[-1] != 2:
            raise ValueError(f"input_traj must be (n_env, N, obs_len, 2), got {input_traj.shape}")
        if input_mask.shape != input_traj.shape[:-1] + (1,):
            raise ValueError(f"input_mask must be (n_env, N, obs_len, 1) = "
                             f"{input_traj.shape[:-1] + (1,)}, got {input_mask.shape}")
        if input_traj.shape[2] != self.config.obs_len:
            raise ValueError(f"the model observes {self.config.obs_len} steps, input_traj has "
                             f"{input_traj.shape[2]}")
        return self._predict(self.params, input_traj=input_traj, input_mask=input_mask)


def from_state_dict(state_dict: Mapping[str, Any], args: Mapping[str, Any], *,
                    step_s: float = CROWDNAV_STEP_S) -> Predictor:
    """A predictor from a gst_updated checkpoint: `state_dict` maps its torch names to arrays
    (`{k: v.numpy() for k, v in checkpoint["model_state_dict"].items()}`), `args` is
    `vars(args)` of its args.pickle."""
    config = model_config(args, step_s)
    params = params_from_torch(state_dict, num_edge_heads=0, ghost=config.ghost, config=config)
    return Predictor(jax.tree.map(jnp.asarray, params), config)


def load(load_path: str | Path, *, step_s: float = CROWDNAV_STEP_S) -> Predictor:
    """A predictor from a CrowdNav++ checkpoint folder (`<load_path>/checkpoint/args.pickle`
    and `epoch_<num_epochs>.pt`, as CrowdNav++ reads them). Reading the .pt needs torch."""
    folder = Path(load_path) / "checkpoint"
    with open(folder / "args.pickle", "rb") as f:
        args = vars(pickle.load(f))
    state_dict = load_state_dict(folder / f"epoch_{args['num_epochs']}.pt")
    return from_state_dict(state_dict, args, step_s=step_s)
