"""The training loss and the training step over a size-packed step (docs/MODEL.md 3).

A step averages the loss of its windows. They come in micro-batches, each padded only to
its own size bucket (`gst_jax.data.pack_step`; on a GPU all in one); the gradients of the
micro-batches are summed, each window weighted 1 / (windows in the step), then Adam updates
once. Every window's random draws depend on its key and its own coordinates only
(`gst_jax.noise`), so the step's loss and gradients are those of the same windows computed
in one padded batch.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import optax

from gst_jax import augment, losses
from gst_jax.config import ModelConfig
from gst_jax.data import PackedStep, SceneBatch
from gst_jax.graph import drop_partially_detected
from gst_jax.model import Params
from gst_jax.parallel import Devices
from gst_jax.rollout import rollout
from gst_jax.training.state import HParams, TrainState, make_optimizer

# The stream of draws of `augment.hide_history`, folded into a step's key.
HIDE_STREAM = 0x41DE


def training_loss(params: Params, key: jax.Array, batch: SceneBatch, config: ModelConfig,
                  hparams: HParams, *, rotate: bool, num_scenes: jax.Array | None = None
                  ) -> jax.Array:
    """Sum of the per-scene training losses of `batch`'s real scenes divided by `num_scenes`
    (default: their count, i.e. their mean). Soft Gumbel samples, dropout on."""
    rotate_key, rollout_key = jax.random.split(key)
    if rotate:
        batch = augment.rotate(rotate_key, batch)
    # A key of its own, so that the rotations and the rollout draw as without the option.
    hide_key = jax.random.fold_in(key, HIDE_STREAM)
    batch = augment.hide_history(hide_key, batch, hparams.hide_history, config.obs_len)
    batch = drop_partially_detected(batch, hparams.fully_detected_only)
    output = rollout(params, rollout_key, batch, config, hparams.controls, hard=False,
                     deterministic=False)
    if num_scenes is None:
        num_scenes = jnp.sum(batch.scene_mask)
    scene_losses = losses.scene_losses(config, output, batch, hparams.score_partial)
    return jnp.sum(scene_losses * batch.scene_mask) / num_scenes


class TrainStep:
    """`step(state, key, packed_step, hparams) -> (state, metrics)`: one optimiser step.

    Two kinds of compiled program: the gradient of one micro-batch added to the running sum
    (one per micro-batch shape, so an epoch compiles one per bucket it meets) and the Adam
    update (one). With `members`, both run over a leading member axis of the state, key and
    hparams (a sweep; the packed step is shared): vmapped, or with `member_map` looped over
    the members inside the one program (`lax.map`: the members' work is not batched, each
    runs the single run's computation). By default (None) they are looped on one CPU, where
    that costs 26 % less than vmapping them, and vmapped elsewhere (docs/benchmarks.md,
    "Sweeps").

    A step whose loss or gradients are not finite leaves the state unchanged and reports
    `finite = False`; the epoch loop decides what that means (stop, or count and go on).

    With `devices`, each micro-batch's scenes are split over them (a sweep's micro-batches
    are copied to every device instead: its members are split); the state, keys and hparams
    must already be placed (`place`).
    """

    def __init__(self, config: ModelConfig, *, rotate: bool = True, members: bool = False,
                 member_map: bool | None = None, devices: Devices | None = None):
        optimizer = make_optimizer()
        self.devices, self.members = devices, members
        if member_map is None:              # members split over devices stay vmapped
            member_map = self.platform == "cpu" and devices is None

        def accumulate(params, key, batch, hparams, num_scenes, loss_sum, grad_sum):
            loss, grads = jax.value_and_grad(training_loss)(
                params, key, batch, config, hparams, rotate=rotate, num_scenes=num_scenes)
            return loss_sum + loss, jax.tree.map(jnp.add, grad_sum, grads)

        def update(state: TrainState, loss, grads, hparams: HParams):
            opt_state = state.opt_state._replace(hyperparams={
                **state.opt_state.hyperparams, "learning_rate": hparams.learning_rate})
            updates, new_opt_state = optimizer.update(grads, opt_state, state.params)
            new_state = TrainState(params=optax.apply_updates(state.params, updates),
                                   opt_state=new_opt_state, step=state.step + 1)
            # The loss, the gradients and the new state must all be finite (a NaN learning
            # rate has finite gradients and NaN parameters).
            finite = jnp.isfinite(loss) & all_finite(grads) & all_finite(new_state)
            state = jax.tree.map(lambda new, old: jnp.where(finite, new, old), new_state, state)
            return state, {"loss": loss, "finite": finite, "grad_norm": optax.tree.norm(grads)}

        def zeros(params):
            return jnp.zeros((), jnp.float32), jax.tree.map(jnp.zeros_like, params)

        if members:
            over_members = _member_map if member_map else jax.vmap
            accumulate = over_members(accumulate, in_axes=(0, 0, None, 0, None, 0, 0))
            update = over_members(update)
            zeros = over_members(zeros)
        self._accumulate = jax.jit(accumulate, donate_argnums=(5, 6))
        self._update = jax.jit(update, donate_argnums=0)
        self._zeros = jax.jit(zeros)

    def loss_and_grads(self, params: Params, key: jax.Array, step: PackedStep, hparams: HParams
                       ) -> tuple[jax.Array, Params]:
        """The step's mean loss and its gradient, summed over the micro-batches."""
        num_scenes = jnp.float32(step.num_scenes)
        loss, grads = self._zeros(params)
        for batch in step.micro_batches:
            if self.devices is not None:
                batch = (self.devices.replicate if self.members else self.devices.split)(batch)
            loss, grads = self._accumulate(params, key, batch, hparams, num_scenes, loss, grads)
        return loss, grads

    def place(self, tree: Any) -> Any:
        """A state, key or hparams tree on the devices: copied to each, or (sweep members,
        leading axis) split over them. Without devices, committed to the default device, as
        a restored checkpoint is: a fresh state and a restored one then share one compiled
        step (uncommitted, a run resumed in the same process compiled its step again)."""
        if self.devices is None:
            return jax.device_put(tree, jax.devices()[0])
        return (self.devices.split if self.members else self.devices.replicate)(tree)

    @property
    def slots_multiple(self) -> int:
        """Micro-batches hold a multiple of this many scenes (those split over devices)."""
        return self.devices.count if self.devices is not None and not self.members else 1

    @property
    def platform(self) -> str:
        """Where the step runs: "cpu", "gpu", ..."""
        devices = self.devices.mesh.devices.flat if self.devices is not None else jax.devices()
        return next(iter(devices)).platform

    @property
    def one_micro_batch(self) -> bool:
        """Whether steps should come as one micro-batch padded to the largest window: on a
        GPU a call costs more than the padding; on a CPU the size buckets are faster."""
        return self.platform != "cpu"

    def __call__(self, state: TrainState, key: jax.Array, step: PackedStep, hparams: HParams
                 ) -> tuple[TrainState, dict]:
        loss, grads = self.loss_and_grads(state.params, key, step, hparams)
        return self._update(state, loss, grads, hparams)


def _member_map(fn, in_axes=0):
    """`fn` over the leading axis of the arguments whose in_axes entry is 0 (the others
    shared), as `jax.vmap` takes it, but looped with `lax.map`."""
    def mapped(*args):
        axes = in_axes if isinstance(in_axes, tuple) else (in_axes,) * len(args)

        def one(per_member):
            given = iter(per_member)
            return fn(*[next(given) if axis == 0 else arg for arg, axis in zip(args, axes)])
        return jax.lax.map(one, [arg for arg, axis in zip(args, axes) if axis == 0])
    return mapped


def all_finite(tree: Any) -> jax.Array:
    """() bool: every floating-point entry of the pytree is finite."""
    return jnp.all(jnp.array([jnp.all(jnp.isfinite(leaf)) for leaf in jax.tree.leaves(tree)
                              if jnp.issubdtype(leaf.dtype, jnp.floating)]))


def make_train_step(config: ModelConfig, *, rotate: bool = True, members: bool = False,
                    member_map: bool | None = None, devices: Devices | None = None
                    ) -> TrainStep:
    """The training step of `config` (see TrainStep); already jit-compiled per shape.

    The last one made is kept: tracing the model takes longer than loading its programs from
    the persistent cache, so runs of one configuration trained one after another in a
    process (tests, notebooks) trace it once, however the arguments are spelled. Only one:
    each compiled program holds memory maps, of which a process may hold 65530
    (docs/commands.md)."""
    return _last_train_step(config, rotate, members, member_map, devices)


@functools.lru_cache(maxsize=1)
def _last_train_step(config: ModelConfig, rotate: bool, members: bool,
                     member_map: bool | None, devices: Devices | None) -> TrainStep:
    return TrainStep(config, rotate=rotate, members=members, member_map=member_map,
                     devices=devices)
