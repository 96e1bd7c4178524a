"""A drop-in for CrowdNav++'s trajectory predictor: its `gst_updated` GST, in mean mode.

CrowdNav++ (github.com/Shuijing725/CrowdNav_Prediction_AttnGraph) calls
`CrowdNavPredInterfaceMultiEnv.forward(input_traj, input_mask)` at every simulator step, for
all its environments at once. This module loads the same checkpoints and answers the same
call with the same numbers (docs/MODEL.md 6):

    predictor = gst_jax.crowdnav.load("gst_updated/results/<run>/sj")   # no torch needed
    predictor = gst_jax.crowdnav.load("pretrained:crowdnav_sj")   # that checkpoint, shipped
    output_traj, output_mask = predictor(input_traj, input_mask)

input_traj (n_env, N, obs_len, 2) positions, -999 where a human is not detected;
input_mask (n_env, N, obs_len, 1) 1 where detected. output_traj (n_env, N, pred_len, 5):
per predicted step the absolute mean position, then the standard deviations and the
correlation of the position accumulated over the steps; -999 positions for the humans not
predicted. output_mask (n_env, N, 1): 1 for the humans predicted. Its quirks are kept: a
displacement counts from step t - 1 to t where the human is detected at t - 1 and at the last
observed step (CrowdNav++ builds the mask so, not from t), and the accumulated Gaussian of a
human not predicted is that of a zero state, not masked.

The predictor refuses, in one line naming environment, human and step (`DataError`), a mask
other than 0 or 1 and a non-finite position where the mask is 1: inside the model one NaN
would spread to every human of its environment, silently. Refusing is the default because a
planner that dropped the detection instead would plan as if that person were not there;
`non_finite="undetected"` opts into reading such a detection as missed (mask 0 and position
-999 there, as CrowdNav++ marks a missed detection), for trackers that mark lost tracks with
NaN. A non-finite position where the mask is 0 is read as -999 in both modes. N = 0 humans
gives empty outputs. The checks are numpy on the host before the jitted call (about 10 us for
16 environments of 20 humans); the pure `predict` underneath does not check.

The call is jitted once per input shape; underneath it is `predict(params, config,
input_traj, input_mask)`, a pure function that can be vmapped or called inside a jitted
planner. gst_jax serves CrowdNav++'s configuration: full connection (no edge selector), any
encoder depth and width, `lstm` or `faster_lstm`; its edge selector for n > 0 is another
design than the paper's and is refused.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any, Literal, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import EVAL_TAU, ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.errors import DataError
from gst_jax.interop import (
    check_state_dict,
    load_state_dict,
    params_from_torch,
)
from gst_jax.model import Controls, Params, weights
from gst_jax.rollout import rollout
from gst_jax.safe_pickle import read_args

MISSING = -999.0
# CrowdNav++'s simulator step: gst_updated's args do not record it.
CROWDNAV_STEP_S = 0.25
NON_FINITE = ("raise", "undetected")


# gst_updated's args that gst_jax reads, and their ranges (`gst_jax.model.weights`): a value
# out of range is refused in one line naming args.pickle, the field and the value.
ARGS_FIELDS: dict[str, weights.Check] = {
    "temporal": weights.one_of(lambda: ("lstm", "faster_lstm")),
    "embedding_size": weights.MODEL_FIELDS["node_dim"],
    "spatial_num_layers": weights.MODEL_FIELDS["encoder_layers"],
    "spatial_num_heads": weights.MODEL_FIELDS["encoder_heads"],
    "lstm_hidden_size": weights.MODEL_FIELDS["lstm_hidden"],
    "obs_seq_len": weights.MODEL_FIELDS["obs_len"],
    "pred_seq_len": weights.MODEL_FIELDS["pred_len"],
    "ghost": weights.boolean, "deterministic": weights.boolean,
    "num_epochs": weights.TRAIN_FIELDS["epochs"], "batch_size": weights.TRAIN_FIELDS["batch_size"],
    "lr": weights.TRAIN_FIELDS["learning_rate"], "init_temp": weights.TRAIN_FIELDS["tau_start"],
    "random_seed": weights.TRAIN_FIELDS["seed"]}
# Those a model needs; a checkpoint folder's args also name its epoch_<num_epochs>.pt, and
# its training (`gst_jax.pretrained.export`).
MODEL_ARGS = ("temporal", "embedding_size", "spatial_num_layers", "spatial_num_heads",
              "lstm_hidden_size", "obs_seq_len", "pred_seq_len", "ghost")
CHECKPOINT_ARGS = MODEL_ARGS + ("num_epochs", "batch_size", "lr", "init_temp", "random_seed")
# What reading a checkpoint's .pt may allocate: never more than PT_MAX_BYTES, nor than
# PT_DECLARED_COPIES times the bytes its zip entries declare (each read as stored, each tensor
# copied as an array: about twice them; four allow a tensor saved twice over one storage). Not
# by its args.pickle: the same folder supplies both, and in-range args (64 layers 4096 wide)
# would allow gigabytes. CrowdNav++'s checkpoints (parameters, Adam's moments, metrics) make
# 1.7 MB; the budget is 150 times that.
PT_MAX_BYTES = 2**28
PT_DECLARED_COPIES = 4


def checked_args(args: Any, where: str = "args", required=MODEL_ARGS) -> Mapping[str, Any]:
    """gst_updated's args (`vars(args)` of its args.pickle), refused in one line naming
    `where` and the field where one of `required` is missing or a field is out of range."""
    if not isinstance(args, Mapping):
        raise DataError(f"{where}: holds a {type(args).__name__}, not gst_updated's args")
    missing = [name for name in required if name not in args]
    if missing:
        raise DataError(f"{where}: has no {missing[0]}, one of gst_updated's args that "
                        "gst_jax reads")
    if problem := weights.field_problem(args, ARGS_FIELDS, known_only=False):
        raise DataError(f"{where}: {problem}")
    if args["embedding_size"] % args["spatial_num_heads"]:
        raise DataError(f"{where}: spatial_num_heads {args['spatial_num_heads']} does not "
                        f"divide embedding_size {args['embedding_size']}")
    return args


def model_config(args: Mapping[str, Any], step_s: float = CROWDNAV_STEP_S,
                 where: str = "args") -> ModelConfig:
    """The ModelConfig of a gst_updated run: `vars(args)` of its `checkpoint/args.pickle`
    (`where` names it in a refusal)."""
    checked_args(args, where)
    if (problem := weights.MODEL_FIELDS["step_s"](step_s)) is not None:
        raise DataError(f"step_s is {weights.shown(step_s)}: {problem}")
    unsupported = {"spatial": "gumbel_social_transformer", "decode_style": "recursive",
                   "lstm_num_layers": 1, "motion_dim": 2, "output_dim": 5,
                   "only_observe_full_period": False, "spatial_num_heads_edges": 0}
    for name, expected in unsupported.items():
        if args.get(name, expected) != expected:
            raise DataError(f"{where}: gst_updated run with {name}="
                            f"{weights.shown(args[name])}: gst_jax serves {name}={expected!r} "
                            "(docs/MODEL.md 6)")
    width = args["embedding_size"]
    return ModelConfig(
        node_dim=width, edge_dim=2 * width, num_edge_heads=0, max_edge_heads=0,
        ghost=args["ghost"], encoder_layers=args["spatial_num_layers"],
        encoder_heads=args["spatial_num_heads"], encoder_ff_dim=128,
        lstm_hidden=args["lstm_hidden_size"],
        output="deterministic" if args.get("deterministic") else "gaussian",
        temporal=args["temporal"], step_s=step_s, obs_len=args["obs_seq_len"],
        pred_len=args["pred_seq_len"])


def checkpoint_args(load_path: str | Path) -> dict[str, Any]:
    """The args of a CrowdNav++ checkpoint folder (`<load_path>/checkpoint/args.pickle`),
    read without running code and checked: every field gst_jax reads, in its range."""
    path = Path(load_path) / "checkpoint" / "args.pickle"
    return dict(checked_args(read_args(path), str(path), CHECKPOINT_ARGS))


def predict(params: Params, config: ModelConfig, input_traj: jax.Array, input_mask: jax.Array
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
    output_mask)`, numpy or jax arrays in, jax arrays out, jitted once per input shape.

    non_finite: "raise" (default) refuses a non-finite position where input_mask is 1;
    "undetected" reads it as a missed detection (see the module docstring).
    """

    params: Params
    config: ModelConfig
    non_finite: Literal["raise", "undetected"] = "raise"

    def __post_init__(self):
        if self.non_finite not in NON_FINITE:
            raise ValueError(f"non_finite must be one of {NON_FINITE}, got {self.non_finite!r}")

    @functools.cached_property
    def _predict(self):
        return jax.jit(functools.partial(predict, config=self.config))

    def __call__(self, input_traj, input_mask) -> tuple[jax.Array, jax.Array]:
        input_traj, input_mask = np.asarray(input_traj), np.asarray(input_mask)
        if input_traj.ndim != 4 or input_traj.shape[-1] != 2:
            raise DataError(f"input_traj must be (n_env, N, obs_len, 2), got {input_traj.shape}")
        if input_mask.shape != input_traj.shape[:-1] + (1,):
            raise DataError(f"input_mask must be (n_env, N, obs_len, 1) = "
                            f"{input_traj.shape[:-1] + (1,)}, got {input_mask.shape}")
        if input_traj.shape[2] != self.config.obs_len:
            raise DataError(f"the model observes {self.config.obs_len} steps, input_traj has "
                            f"{input_traj.shape[2]}")
        num_env, num_humans = input_traj.shape[:2]
        if num_humans == 0:       # nobody in view: nothing to predict (and no program to jit)
            return (jnp.zeros((num_env, 0, self.config.pred_len, 5), jnp.float32),
                    jnp.zeros((num_env, 0, 1), jnp.float32))
        input_traj, input_mask = self._checked(input_traj, input_mask)
        return self._predict(self.params, input_traj=input_traj, input_mask=input_mask)

    def _checked(self, input_traj: np.ndarray, input_mask: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The inputs, refused or repaired where one detection would spread NaN to all."""
        detected = input_mask[..., 0]
        not_binary = (detected != 0) & (detected != 1)
        if not_binary.any():
            env, human, step = np.argwhere(not_binary)[0]
            raise DataError(f"input_mask[env {env}, human {human}, step {step}] is "
                            f"{detected[env, human, step]:g}; input_mask must be 0 or 1")
        if np.isfinite(input_traj).all():
            return input_traj, input_mask
        # Per coordinate, not .all(axis=-1): numpy reduces a length-2 axis ten times slower.
        finite = np.isfinite(input_traj[..., 0]) & np.isfinite(input_traj[..., 1])
        broken = ~finite & (detected == 1)
        if broken.any() and self.non_finite == "raise":
            env, human, step = np.argwhere(broken)[0]
            xy = input_traj[env, human, step]
            raise DataError(f"input_traj[env {env}, human {human}, step {step}] is "
                            f"{xy[~np.isfinite(xy)][0]} where input_mask is 1 (or "
                            "non_finite=\"undetected\" reads such detections as missed)")
        if broken.any():
            input_mask = np.where(broken[..., None], 0, input_mask).astype(input_mask.dtype)
        # Undetected positions are CrowdNav++'s -999: they enter its displacement mask quirk.
        input_traj = np.where(finite[..., None], input_traj, MISSING).astype(input_traj.dtype)
        return input_traj, input_mask


def from_state_dict(state_dict: Mapping[str, Any], args: Mapping[str, Any], *,
                    step_s: float = CROWDNAV_STEP_S,
                    non_finite: Literal["raise", "undetected"] = "raise") -> Predictor:
    """A predictor from a gst_updated checkpoint: `state_dict` maps its torch names to arrays
    (`{k: v.numpy() for k, v in checkpoint["model_state_dict"].items()}`), `args` is
    `vars(args)` of its args.pickle. Both are checked (`checked_args`,
    `gst_jax.interop.check_state_dict`): a refusal is one line naming the field or tensor."""
    return _from_checkpoint(load_state_dict(state_dict), args, step_s, non_finite)


def _from_checkpoint(state_dict: Mapping[str, np.ndarray], args: Mapping[str, Any],
                     step_s: float, non_finite, where: str = "state_dict",
                     args_where: str = "args") -> Predictor:
    config = model_config(args, step_s, args_where)
    check_state_dict(state_dict, config, where)
    params = params_from_torch(state_dict, num_edge_heads=0, ghost=config.ghost, config=config)
    return Predictor(jax.tree.map(jnp.asarray, params), config, non_finite)


def from_run(run, *, non_finite: Literal["raise", "undetected"] = "raise") -> Predictor:
    """A predictor from a gst_jax model of CrowdNav++'s kind (a `gst_jax.runs.Run`: its
    `model_config` and `params`): full connection (no edge selector), the Gaussian output, an
    LSTM. Refuses another kind in one line."""
    return _predictor(run.name, run.model_config, run.params, non_finite)


def _predictor(name: str, config: ModelConfig, params, non_finite) -> Predictor:
    if config.selects_edges or config.output != "gaussian" or not config.recurrent:
        raise ValueError(f"{name}: CrowdNav++'s predictor is a full-connection (n = 0) GST (P) "
                         f"with an LSTM; this model has n = {config.num_edge_heads}, output "
                         f"{config.output!r}, temporal {config.temporal!r}")
    return Predictor(params, config, non_finite)


def load(load_path: str | Path, *, step_s: float = CROWDNAV_STEP_S,
         non_finite: Literal["raise", "undetected"] = "raise") -> Predictor:
    """A predictor from a CrowdNav++ checkpoint folder (`<load_path>/checkpoint/args.pickle`
    and `epoch_<num_epochs>.pt`, as CrowdNav++ reads them), read by `gst_jax.safe_pickle`:
    no torch needed, and a file that would run code is refused. Or from a shipped model,
    `pretrained:crowdnav_sj` (CrowdNav++'s `..._seed1000/sj` checkpoint, converted) or
    `pretrained:crowdnav_sj_rand` (`..._seed1000_rand/sj`), or any weights folder of
    `gst_jax.model.weights` (`python -m gst_jax.pretrained export ... --out DIR`), whose
    config.json gives the time step (`step_s` is for CrowdNav++'s folders).

    A checkpoint folder is checked before it is used, each refusal one line naming the file
    and the field or tensor (`DataError`): args.pickle's fields in their ranges
    (`checked_args`), the .pt read within a fixed budget and what its own zip entries declare
    (PT_MAX_BYTES, PT_DECLARED_COPIES: a tensor or a zip entry beyond it is refused before it
    is allocated), and its state dict holding every tensor of that model, of its shape, finite
    (`gst_jax.interop.check_state_dict`)."""
    if weights.is_weights(load_path):
        loaded = weights.load(load_path)
        return _predictor(str(load_path), loaded.model_config, loaded.params, non_finite)
    args = checkpoint_args(load_path)
    args_path = Path(load_path) / "checkpoint" / "args.pickle"
    model_config(args, step_s, str(args_path))       # refused before the .pt is read
    pt = args_path.parent / f"epoch_{args['num_epochs']}.pt"
    state_dict = load_state_dict(pt, PT_MAX_BYTES, "gst_jax.crowdnav.PT_MAX_BYTES",
                                 PT_DECLARED_COPIES)
    return _from_checkpoint(state_dict, args, step_s, non_finite, str(pt), str(args_path))
