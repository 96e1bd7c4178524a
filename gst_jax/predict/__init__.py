"""Jitted prediction: K samples of every pedestrian's next 12 positions.

    predict = make_predict(config, num_samples=20)
    prediction = predict(params, key, batch)        # compiled once per batch shape

Samples are a `vmap` over split keys; the observed steps' edge probabilities, which do not
depend on the sample, are computed once. Evaluation protocol (docs/MODEL.md 4): hard Gumbel
samples at tau = 0.03, no dropout; GST (P) also samples its Gaussian.

Memory: before a batch shape first runs, XLA's estimate of its compiled program is compared
with a budget and with the memory this process may still take; a program over either
computes its samples in chunks, with the same samples, and one that cannot fit even one
sample at a time is refused in one line before anything is allocated (`chunking`,
docs/scaling.md). Before each compile the memory left must hold XLA's compiler, and a large
crowd with the exact model is announced in one line before its first call (`checks`, which
also serves any jitted program over a crowd: `compile_checked`).

    chunking.py  `Chunking` and `choose`: the samples at once within the memory
    cost.py      XLA's estimate of a compiled program's memory, the count of its arithmetic
    checks.py    room for the compiler and the program, the large crowd's notice

Their public names are re-exported here. The constants a test or a benchmark may change
(`COMPILER_BYTES`, `CANDIDATES_PAY_ABOVE`, ...) are read in the module that defines them, and
the memory available in `gst_jax.resources`.
"""

from __future__ import annotations

import warnings
from typing import Any

import flax
import jax
import jax.numpy as jnp
import numpy as np

# compiles is imported for its effect: every persistent compilation cache this process opens
# checks its entries (`gst_jax.compiles.check_cache_entries`), however its folder was set.
from gst_jax import compiles, resources  # noqa: F401
from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.model import Controls, Params
from gst_jax.predict import chunking as _chunking
from gst_jax.predict.checks import (
    CANDIDATES_PAY_ABOVE,
    COMPILER_BYTES,
    CPU_OPERATIONS_PER_CORE_SECOND,
    LONG_CALL_S,
    SUGGESTED_CANDIDATES,
    check_compiler_room,
    check_memory,
    compile_checked,
    crowd_notice,
)
from gst_jax.predict.chunking import CHUNKING_SLACK, DEFAULT_MEMORY_BUDGET, Chunking
from gst_jax.predict.cost import CPU_RUNTIME_MARGIN, Estimate, devices_of, estimate, operation_count
from gst_jax.resources import CGROUP_ROOT, NO_LIMIT, available_memory, cgroup_headroom
from gst_jax.rollout import observed_edge_probabilities, rollout

__all__ = [
    "Prediction", "make_predict", "Predictor",
    # re-exported: chunking.py, cost.py, checks.py and gst_jax.resources
    "Chunking", "DEFAULT_MEMORY_BUDGET", "CHUNKING_SLACK",
    "Estimate", "estimate", "operation_count", "CPU_RUNTIME_MARGIN",
    "check_compiler_room", "check_memory", "crowd_notice", "compile_checked", "COMPILER_BYTES",
    "SUGGESTED_CANDIDATES", "CANDIDATES_PAY_ABOVE", "LONG_CALL_S",
    "CPU_OPERATIONS_PER_CORE_SECOND",
    "available_memory", "cgroup_headroom", "CGROUP_ROOT", "NO_LIMIT",
]


@flax.struct.dataclass
class Prediction:
    """K sampled futures of B scenes. S = obs_len + pred_len - 1 selector calls.

    positions: (K, B, P, N, 2) positions (the frame of the observations); NaN for pedestrians
      not predicted, so that nobody mistakes them for predictions.
    displacements: (K, B, P, N, 2) per-step displacements.
    mu, sigma: (K, B, P, N, 2); corr: (K, B, P, N) Gaussian parameters (GST (P) samples them).
    sampled_adjacency: (K, B, S, N, N+1) sampled neighbours per target (ghost last), or None.
    edge_probs: (K, B, S, N, G, N+1) edge probabilities per head slot, or None.
    predicted_mask: (B, N) 1 for the pedestrians predicted: those detected at both of the
      last two observed steps (their last displacement exists; docs/MODEL.md 2.3).
    """

    positions: jax.Array
    displacements: jax.Array
    mu: jax.Array
    sigma: jax.Array
    corr: jax.Array
    sampled_adjacency: jax.Array | None
    edge_probs: jax.Array | None
    predicted_mask: jax.Array


def make_predict(config: ModelConfig, num_samples: int = 20, *, with_graph: bool = True,
                 mean: bool = False, memory_budget_bytes: int = DEFAULT_MEMORY_BUDGET
                 ) -> Predictor:
    """Build `predict(params, key, batch, controls=None) -> Prediction`, jitted per shape.

    `controls` overrides the traced switches (n, ghost, tau); by default the config's n and
    ghost with tau = 0.03. `with_graph=False` drops the per-step graphs (they dominate memory
    for large K and N) when only trajectories are needed. `mean=True` predicts every step as
    the mean of the head's Gaussian (GST (P) without sampling its displacements). A batch
    holds T = obs_len observed steps (`make_batch`), or obs_len + pred_len (windows with
    their future, evaluation). memory_budget_bytes: what one call's program may use; larger
    problems compute their samples in chunks, with the same samples (`chunking`).
    """
    if num_samples < 1:
        raise ValueError(f"num_samples must be at least 1, got {num_samples}")
    if memory_budget_bytes < 1:
        raise ValueError(f"memory_budget_bytes must be positive, got {memory_budget_bytes}")
    return Predictor(config, num_samples, with_graph, mean, memory_budget_bytes)


class Predictor:
    """`make_predict`'s function: a chunking per batch shape, chosen on its first call, and
    one jitted program per chunking. Inside the caller's `jit` or `vmap` it is the single
    vmap over samples, unchecked: the caller's program is the caller's to size."""

    def __init__(self, config: ModelConfig, num_samples: int, with_graph: bool, mean: bool,
                 memory_budget_bytes: int):
        self.config, self.num_samples = config, num_samples
        self.with_graph, self.mean = with_graph, mean
        self.memory_budget_bytes = memory_budget_bytes
        self._programs: dict[tuple[int, int | None], Any] = {}
        self._chunkings: dict[tuple, Chunking] = {}

    def __call__(self, params: Params, key: jax.Array, batch: SceneBatch,
                 controls: Controls | None = None) -> Prediction:
        args = (params, key, batch, controls)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(args)):
            return self._program(self.num_samples, None)(*args)
        chunking = self.chunking(*args)
        return self._program(chunking.samples_at_once, chunking.observed_steps_at_once)(*args)

    def chunking(self, params: Params, key: jax.Array, batch: SceneBatch,
                 controls: Controls | None = None) -> Chunking:
        """The chunking of this batch's shape, chosen (and compiled) on its first call, which
        announces a large crowd (`crowd_notice`)."""
        signature = (tuple(np.shape(leaf) for leaf in jax.tree.leaves(batch)), controls is None)
        if signature not in self._chunkings:
            chosen = self._choose((params, key, batch, controls))
            self._chunkings[signature] = chosen
            if notice := crowd_notice(self.config, batch.positions.shape[2], chosen,
                                      devices_of(batch.positions)[0], self._work(batch)):
                warnings.warn(notice, stacklevel=3)
        return self._chunkings[signature]

    def _choose(self, args) -> Chunking:
        """The fastest chunking within the budget and the memory available
        (`chunking.choose`)."""
        available = resources.available_memory(devices_of(args[2].positions)[0])
        return _chunking.choose(
            lambda samples_at_once, observed_steps_at_once: self._measure(
                samples_at_once, observed_steps_at_once, args),
            self.num_samples, self.memory_budget_bytes, available, self._work(args[2]))

    def _work(self, batch: SceneBatch) -> str:
        """"predicting 20 samples of a scene of 300 people", for one-line messages."""
        return f"predicting {self.num_samples} samples of {_scenes(batch, self.config.obs_len)}"

    def _measure(self, samples_at_once: int, observed_steps_at_once: int | None,
                 args) -> Chunking:
        """Compile a chunking's program for these arguments (jit's cache keeps it: the call
        that follows does not compile again) and read XLA's estimate of it; refused first
        where the memory left cannot hold the compiler."""
        program = self._program(samples_at_once, observed_steps_at_once)
        batch = args[2]
        devices = devices_of(batch.positions)
        check_compiler_room(self._work(batch), devices[0])
        traced = program.trace(*args)
        return Chunking(samples_at_once, observed_steps_at_once,
                        *estimate(traced.lower().compile(), traced.jaxpr, devices))

    def _program(self, samples_at_once: int, observed_steps_at_once: int | None):
        chunking = (samples_at_once, observed_steps_at_once)
        if chunking not in self._programs:
            self._programs[chunking] = _jitted_predict(
                self.config, self.num_samples, self.with_graph, self.mean, *chunking)
        return self._programs[chunking]


def _jitted_predict(config: ModelConfig, num_samples: int, with_graph: bool, mean: bool,
                    samples_at_once: int, observed_steps_at_once: int | None):
    """The jitted predict of one chunking; sample k uses key k of `split(key, num_samples)`
    in every chunking, so that they all draw the same samples."""
    steps = (config.obs_len, config.obs_len + config.pred_len)

    @jax.jit
    def predict(params: Params, key: jax.Array, batch: SceneBatch,
                controls: Controls | None = None) -> Prediction:
        if batch.positions.shape[1] not in steps:
            raise ValueError(f"the batch has {batch.positions.shape[1]} steps; expected "
                             f"{steps[0]} observed steps (or {steps[1]} with the future)")
        if controls is None:
            controls = Controls.from_config(config)

        # The observed steps' edge probabilities do not depend on the sample: computed once.
        observed_probs = (observed_edge_probabilities(params, batch, config, controls,
                                                      steps_at_once=observed_steps_at_once)
                          if config.selects_edges else None)

        def one_sample(sample_key):
            out = rollout(params, sample_key, batch, config, controls, hard=True,
                          deterministic=True, observed_edge_probs=observed_probs, mean=mean)
            graph = (out.sampled_edges.sum(axis=-2), out.edge_probs) if with_graph else (None, None)
            return out.displacements, out.mu, out.sigma, out.corr, graph

        keys = jax.random.split(key, num_samples)
        # lax.map vmaps within a chunk and loops over chunks: memory of one chunk at a time.
        sampled = (jax.vmap(one_sample)(keys) if samples_at_once == num_samples
                   else jax.lax.map(one_sample, keys, batch_size=samples_at_once))
        displacements, mu, sigma, corr, (adjacency, probs) = sampled
        keep = batch.predicted_mask(config.obs_len)
        last_position = batch.positions[:, config.obs_len - 1] * keep[..., None]
        positions = jnp.where(keep[:, None, :, None] > 0,
                              last_position[:, None] + jnp.cumsum(displacements, axis=2), jnp.nan)
        return Prediction(positions=positions, displacements=displacements, mu=mu, sigma=sigma,
                          corr=corr, sampled_adjacency=adjacency, edge_probs=probs,
                          predicted_mask=keep)

    return predict


def _scenes(batch: SceneBatch, obs_len: int) -> str:
    """"a scene of 300 people", "4 scenes of up to 30 people in 48 slots": who is observed in
    `batch` (and the slots of its program, which its cost follows, where they are more)."""
    seen = np.asarray(batch.position_mask)[:, :obs_len].any(axis=1).sum(axis=-1)
    people = int(seen.max()) if seen.size else 0
    slots = np.shape(batch.position_mask)[-1]
    return (f"a scene of {people} people" if len(seen) == 1
            else f"{len(seen)} scenes of up to {people} people"
            + (f" in {slots} slots" if slots > people else ""))
