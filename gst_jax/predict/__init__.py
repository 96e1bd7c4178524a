"""Jitted prediction: K samples of every pedestrian's next 12 positions.

    predict = make_predict(config, num_samples=20)
    prediction = predict(params, key, batch)        # compiled once per batch shape

Samples are a `vmap` over split keys; the observed steps' edge probabilities, which do not
depend on the sample, are computed once. Evaluation protocol (docs/MODEL.md 4): hard Gumbel
samples at tau = 0.03, no dropout; GST (P) also samples its Gaussian.

Memory: the edge selector attends over (N + 1)^2 neighbour pairs for each of N targets, so a
call grows as K N^3 (N = 300, K = 20: 9.3 GiB, 6.2 GiB of it one buffer). Before a batch
shape first runs, XLA's estimate of its compiled program is compared with a budget and with
the memory this process may still take; a program over either computes its samples in
chunks (`lax.map`, a vmap within each) and the observed steps one at a time, with the same
keys and so the same samples; one that cannot fit even one sample at a time is refused in
one line (`DataError`) before anything is allocated (docs/scaling.md).

Before each compile, the memory left (the least of MemAvailable, the cgroup limit's headroom
and the address-space limit's) must hold XLA's compiler too (`COMPILER_BYTES`); a process
that cannot is refused in one line instead of dying inside LLVM. On a CPU, a crowd above
`CANDIDATES_PAY_ABOVE` people with the exact model whose call is expected to take a second
or more is announced in one line (a warning) before its first call, with its expected time
(`operation_count`) and XLA's estimate of its memory, naming the option that makes it
cheap, candidates= (`crowd_notice`). `compile_checked` does all this for any jitted program
over a crowd (a stream's step).
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import flax
import jax
import jax.numpy as jnp
import numpy as np

from gst_jax.config import ModelConfig
from gst_jax.data import SceneBatch
from gst_jax.errors import DataError
from gst_jax.model import Controls
from gst_jax.rollout import observed_edge_probabilities, rollout

# What one call's program may use by default, chunking its samples to stay within it:
# N = 300, K = 20 then runs 2 samples at a time (1.1 GiB, 1.6 GiB peak for the process) instead
# of all 20 (8.9 GiB); up to N = 128 at K = 20 (0.7 GiB) it keeps the single vmap over samples.
DEFAULT_MEMORY_BUDGET = 3 * 2 ** 29
# XLA's estimate leaves out the scratch the CPU runtime takes while a call runs, about one
# (N, N+1, N+1) float32 array per sample at once: measured up to 39 % more at N = 300, 11 % at
# N = 200 (benchmarks/bench_memory.py), so a CPU's need is taken as the estimate times this.
CPU_RUNTIME_MARGIN = 1.4
# A chunking is chosen this far below the target, so that the first one measured fits.
CHUNKING_SLACK = 0.95
CGROUP_ROOT = Path("/sys/fs/cgroup")
# cgroup v1 writes "no limit" as a huge number (PAGE_COUNTER_MAX pages).
NO_LIMIT = 2 ** 60
# What XLA's compiler itself takes beyond the process's memory while it compiles a predict
# program (its threads, LLVM's code sections); a process with less left died inside it
# (`std::bad_alloc`, "LLVM ERROR: Unable to allocate section memory!" or "pthread_create
# failed", a segfault), and with 32 MiB left even loading a compiled program from the
# persistent cache did. Measured as the address space that compiling and running a first
# predict (N = 8, K = 3) needed above the process's size (2-core VM, jaxlib 0.10.2, a limit
# set with setrlimit): 128-160 MiB at XLA's default optimisation level, 192-256 MiB at
# --xla_backend_optimization_level=0 (the test suite's); N = 300, K = 20 compiled its single
# vmap with 256 MiB left.
COMPILER_BYTES = 256 * 2 ** 20
# The candidate neighbourhood a large crowd is pointed to (docs/MODEL.md 2.4), and the crowd
# above which it predicts faster than the exact model: the paper's model, one sample, median
# call (2-core VM loaded by other work, CPU time): N = 24 14.7 / 11.2 ms, 32 25.5 / 18.7 ms
# (the wall-clock medians tie there), 48 70.7 / 24.0 ms, 64 163 / 41 ms, 300 15.9 / 0.29 s
# (docs/benchmarks.md, benchmarks/bench_neighbourhood.py).
SUGGESTED_CANDIDATES = 16
CANDIDATES_PAY_ABOVE = 32
# A call expected to take this long or more is worth a word (a choice, not a measurement;
# a robot's stream passes its model's step).
LONG_CALL_S = 1.0
# A predict program's arithmetic (`operation_count`) per second of one CPU core: 12.7-18.7 G
# per second of CPU time on the same VM over N = 16-300, exact and with 16 candidates; 12.7 G
# for the exact model at N = 300 (bench_neighbourhood.py's g_operations_per_cpu_s). The
# slowest, so that a call's expected time errs long.
CPU_OPERATIONS_PER_CORE_SECOND = 12.7e9


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
    sampled_adjacency: Any
    edge_probs: Any
    predicted_mask: jax.Array


class Estimate(NamedTuple):
    """What a compiled program needs: `Chunking`'s xla_bytes, bytes_needed and operations."""

    xla_bytes: int | None
    bytes_needed: int | None
    operations: float


@dataclasses.dataclass(frozen=True)
class Chunking:
    """How the program of one batch shape computes, and what XLA says it needs.

    samples_at_once: samples vmapped together, looped over chunks (K: one vmap).
    observed_steps_at_once: observed steps per edge-selector call (None: all at once).
    xla_bytes: temporaries + arguments + outputs of the compiled program, over every device
      of a CPU (they share its memory); None where XLA does not say.
    bytes_needed: what a call takes: xla_bytes, times CPU_RUNTIME_MARGIN on a CPU.
    operations: the program's arithmetic (`operation_count`), what its time grows with.
    """

    samples_at_once: int
    observed_steps_at_once: int | None
    xla_bytes: int | None
    bytes_needed: int | None
    operations: float = 0.0


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
    problems compute their samples in chunks, with the same samples (module docstring).
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

    def __call__(self, params, key: jax.Array, batch: SceneBatch,
                 controls: Controls | None = None) -> Prediction:
        args = (params, key, batch, controls)
        if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(args)):
            return self._program(self.num_samples, None)(*args)
        chunking = self.chunking(*args)
        return self._program(chunking.samples_at_once, chunking.observed_steps_at_once)(*args)

    def chunking(self, params, key: jax.Array, batch: SceneBatch,
                 controls: Controls | None = None) -> Chunking:
        """The chunking of this batch's shape, chosen (and compiled) on its first call, which
        announces a large crowd (`crowd_notice`)."""
        signature = (tuple(np.shape(leaf) for leaf in jax.tree.leaves(batch)), controls is None)
        if signature not in self._chunkings:
            chosen = self._choose((params, key, batch, controls))
            self._chunkings[signature] = chosen
            if notice := crowd_notice(self.config, batch.positions.shape[2], chosen,
                                      _devices(batch.positions)[0], self._work(batch)):
                warnings.warn(notice, stacklevel=3)
        return self._chunkings[signature]

    def _choose(self, args) -> Chunking:
        """The fastest chunking within the budget (and the memory available): today's single
        vmap if it fits, else as many samples at once as fit, observing step by step."""
        num_samples = self.num_samples
        available = available_memory(_devices(args[2].positions)[0])
        budget = self.memory_budget_bytes
        target = budget if available is None else min(budget, available[0])
        whole = self._measure(num_samples, None, args)
        if whole.bytes_needed is None or whole.bytes_needed <= target:
            return whole
        least = self._measure(1, 1, args)
        if available is not None and least.bytes_needed > available[0]:
            raise DataError(_refusal(num_samples, args[2], self.config.obs_len,
                                     least.bytes_needed, *available))
        # The need grows linearly with the samples at once (XLA: 0.16 + 0.31 c GiB at
        # N = 300); the slope through `whole` overestimates it where the observed steps at
        # once dominate, and every candidate is measured before it is chosen.
        per_sample = (whole.bytes_needed - least.bytes_needed) / max(num_samples - 1, 1)
        while True:
            room = CHUNKING_SLACK * target - least.bytes_needed
            chunk = min(num_samples, 1 + int(room // max(per_sample, 1)))
            if chunk <= 1:
                return least
            candidate = self._measure(chunk, 1, args)
            if candidate.bytes_needed <= target:
                return candidate
            per_sample = (candidate.bytes_needed - least.bytes_needed) / (chunk - 1)

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
        devices = _devices(batch.positions)
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
    def predict(params, key: jax.Array, batch: SceneBatch,
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


def _devices(array) -> list[jax.Device]:
    """The devices holding `array`, by id (the default device for a host array)."""
    devices = getattr(getattr(array, "sharding", None), "device_set", None)
    return sorted(devices, key=lambda d: d.id) if devices else jax.devices()[:1]


def _scenes(batch: SceneBatch, obs_len: int) -> str:
    """"a scene of 300 people", "4 scenes of up to 30 people in 48 slots": who is observed in
    `batch` (and the slots of its program, which its cost follows, where they are more)."""
    seen = np.asarray(batch.position_mask)[:, :obs_len].any(axis=1).sum(axis=-1)
    people = int(seen.max()) if seen.size else 0
    slots = np.shape(batch.position_mask)[-1]
    return (f"a scene of {people} people" if len(seen) == 1
            else f"{len(seen)} scenes of up to {people} people"
            + (f" in {slots} slots" if slots > people else ""))


def _refusal(num_samples: int, batch: SceneBatch, obs_len: int, needed: int, available: int,
             source: str) -> str:
    """The one line that refuses a prediction that cannot fit."""
    return (f"predicting {num_samples} samples of {_scenes(batch, obs_len)} needs "
            f"{_size(needed)} at least (one sample at a time); {_size(available)} is available "
            f"({source}); use fewer people per scene or more memory")


def estimate(compiled, closed_jaxpr, devices: list[jax.Device]) -> Estimate:
    """What a program needs on `devices`: XLA's estimate of the memory of its compiled form
    (None where XLA does not say) and the arithmetic of its (closed) jaxpr."""
    operations = operation_count(closed_jaxpr.jaxpr)
    stats = compiled.memory_analysis()
    if stats is None:
        return Estimate(None, None, operations)
    on_cpu = devices[0].platform == "cpu"
    # Host devices of one CPU (XLA_FLAGS device count) share its memory.
    xla_bytes = (len(devices) if on_cpu else 1) * (
        stats.temp_size_in_bytes + stats.argument_size_in_bytes + stats.output_size_in_bytes)
    return Estimate(xla_bytes, int(xla_bytes * CPU_RUNTIME_MARGIN) if on_cpu else xla_bytes,
                    operations)


def operation_count(jaxpr) -> float:
    """The arithmetic of a jaxpr (`jax.core.Jaxpr`): 2 per multiply-add of a matrix product,
    one per element read or written by any other operation (the larger); a scan's body times
    its length, a while loop's once, the larger branch of a cond. (XLA's own count,
    `cost_analysis`, takes every loop's body once, and predict's are where its time goes:
    the rollout's scan over the predicted steps, `lax.map` over chunks of samples.)"""
    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            (contracting, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += 2.0 * _elements(eqn.outvars[0].aval) * math.prod(lhs[a] for a in contracting)
            continue
        inner = [getattr(sub, "jaxpr", sub) for param in eqn.params.values()
                 for sub in (param if isinstance(param, (list, tuple)) else [param])
                 if hasattr(getattr(sub, "jaxpr", sub), "eqns")]
        if not inner:
            total += max(_elements(v.aval) for v in (*eqn.invars, *eqn.outvars))
            continue
        counts = [operation_count(sub) for sub in inner]
        if name == "cond":
            total += max(counts)
        else:
            total += (eqn.params["length"] if name == "scan" else 1) * sum(counts)
    return total


def _elements(aval) -> int:
    return math.prod(getattr(aval, "shape", ()))


def check_compiler_room(what: str, device: jax.Device | None = None) -> None:
    """Refuse in one line (`DataError`) where the memory this process may still take on
    `device` (the default device) cannot hold XLA's compiler (`COMPILER_BYTES`): compiling
    there dies inside LLVM without a word. `what`: the work, for the message ("predicting 20
    samples of ...")."""
    available = available_memory(device or jax.devices()[0])
    if available is not None and available[0] < COMPILER_BYTES:
        left, source = available
        raise DataError(f"{what}: XLA's compiler needs about {_size(COMPILER_BYTES)} more "
                        f"than this process holds, and {_size(left)} is left ({source}); "
                        "raise the limit")


def crowd_notice(config: ModelConfig, slots: int, cost: Estimate | Chunking,
                 device: jax.Device, what: str, slower_than_s: float | None = None
                 ) -> str | None:
    """The one line announcing a large crowd, or None: on a CPU, the exact model
    (`config.candidates` 0) over more than CANDIDATES_PAY_ABOVE people (slots: the program's
    pedestrian axis) where a call is expected to take `slower_than_s` (default LONG_CALL_S)
    or more. It gives what a call of the program about to run needs (`cost`: XLA's estimate
    of its memory; its time, its arithmetic at CPU_OPERATIONS_PER_CORE_SECOND on the cores
    this process may use, which other work slows) and the option that makes it cheap.
    `what`: the work ("predicting 20 samples of a scene of 300 people")."""
    if config.candidates or slots <= CANDIDATES_PAY_ABOVE or device.platform != "cpu":
        return None
    cores = _usable_cores()
    seconds = cost.operations / (CPU_OPERATIONS_PER_CORE_SECOND * cores)
    if seconds < (LONG_CALL_S if slower_than_s is None else slower_than_s):
        return None
    memory = "" if cost.bytes_needed is None else (
        f" and {_size(cost.bytes_needed)} (XLA's estimate)")
    return (f"{what} with the exact model needs about {_seconds(seconds)} a call on {cores} "
            f"idle CPU core{'s' if cores > 1 else ''}{memory}; above "
            f"{CANDIDATES_PAY_ABOVE} people the candidate neighbourhood is faster: "
            f"candidates={SUGGESTED_CANDIDATES} (--candidates {SUGGESTED_CANDIDATES}; "
            "docs/MODEL.md 2.4)")


def compile_checked(program, args: tuple, config: ModelConfig, slots: int, what: str,
                    slower_than_s: float | None = None) -> Estimate:
    """Before the jitted `program` first runs on `args` over a crowd of `slots` people (a
    stream's step at a new capacity): refuse in one line where the memory left cannot hold
    the compiler; compile it (jit's cache keeps it: the call that follows does not compile
    again); refuse in one line where XLA's estimate of a call exceeds the memory available;
    warn in one line where the crowd is large for the exact model and a call is expected to
    take `slower_than_s` or more (`crowd_notice`; a robot's stream: its model's step_s).
    Returns the estimate. `what` names the work in those lines ("a stream step over 320
    slots")."""
    leaves = [leaf for leaf in jax.tree.leaves(args) if hasattr(leaf, "shape")]
    devices = _devices(leaves[0]) if leaves else jax.devices()[:1]
    check_compiler_room(what, devices[0])
    traced = program.trace(*args)
    cost = estimate(traced.lower().compile(), traced.jaxpr, devices)
    available = available_memory(devices[0])
    if available is not None and cost.bytes_needed is not None and (
            cost.bytes_needed > available[0]):
        raise DataError(f"{what} needs {_size(cost.bytes_needed)} (XLA's estimate); "
                        f"{_size(available[0])} is available ({available[1]}); use fewer "
                        f"people, candidates={SUGGESTED_CANDIDATES} or more memory")
    if notice := crowd_notice(config, slots, cost, devices[0], what, slower_than_s):
        warnings.warn(notice, stacklevel=2)
    return cost


def _usable_cores() -> int:
    """The CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:                                  # not Linux
        return os.cpu_count() or 1


def _seconds(seconds: float) -> str:
    if seconds >= 120:
        return f"{seconds / 60:.0f} min"
    return f"{seconds:.2g} s" if seconds < 10 else f"{seconds:.0f} s"


def _size(num_bytes: int) -> str:
    for unit, power, digits in (("GiB", 30, 1), ("MiB", 20, 0), ("KiB", 10, 0)):
        if num_bytes >= 2 ** power:
            return f"{num_bytes / 2 ** power:.{digits}f} {unit}"
    return f"{max(num_bytes, 0)} bytes"


def available_memory(device: jax.Device) -> tuple[int, str] | None:
    """(bytes this process may still allocate on `device`, where that figure comes from), or
    None where unknown. A CPU: the least of the machine's MemAvailable, what is left under
    this process's cgroup limits and under its address-space limit (`ulimit -v`)."""
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" not in stats:
            return None
        return stats["bytes_limit"] - stats.get("bytes_in_use", 0), f"free on {device}"
    candidates = []
    if (meminfo := _read_kib("/proc/meminfo", "MemAvailable:")) is not None:
        candidates.append((meminfo, "MemAvailable of this machine"))
    try:
        proc_cgroup = Path("/proc/self/cgroup").read_text()
    except OSError:
        proc_cgroup = ""
    if headrooms := _cgroup_headrooms(proc_cgroup, CGROUP_ROOT):
        left, limit = min(headrooms)
        candidates.append((left, f"under this process's cgroup memory limit of {_size(limit)}"))
    if (address_space := _address_space_left()) is not None:
        left, limit = address_space
        candidates.append((left, f"under this process's address-space limit of "
                                 f"{_size(limit)}, ulimit -v"))
    return min(candidates) if candidates else None


def _address_space_left() -> tuple[int, int] | None:
    """(what `ulimit -v` (RLIMIT_AS) leaves this process, the limit); None without one."""
    try:
        import resource                                     # POSIX only
    except ImportError:
        return None
    limit, _ = resource.getrlimit(resource.RLIMIT_AS)
    if limit == resource.RLIM_INFINITY:
        return None
    return limit - (_read_kib("/proc/self/status", "VmSize:") or 0), limit


def cgroup_headroom(proc_cgroup: str, root: Path) -> int | None:
    """What this process's memory cgroups (`/proc/self/cgroup` text, mounted at `root`) and
    their parents still admit: the least of limit - (usage - inactive file pages), which the
    kernel reclaims before it kills; None where no limit is set. cgroup v2 and v1."""
    headrooms = _cgroup_headrooms(proc_cgroup, root)
    return min(headrooms)[0] if headrooms else None


def _cgroup_headrooms(proc_cgroup: str, root: Path) -> list[tuple[int, int]]:
    """(headroom, limit) of every limited memory cgroup of this process and its parents."""
    headroom = []
    for line in proc_cgroup.splitlines():
        if line.count(":") < 2:
            continue
        _, controllers, path = line.split(":", 2)
        if controllers == "":
            directory, files = root, ("memory.max", "memory.current", "inactive_file")
        elif "memory" in controllers.split(","):
            directory, files = root / "memory", ("memory.limit_in_bytes",
                                                 "memory.usage_in_bytes", "total_inactive_file")
        else:
            continue
        parts = [part for part in path.split("/") if part]
        for depth in range(len(parts), -1, -1):
            limit, usage, inactive = _cgroup_files(directory.joinpath(*parts[:depth]), files)
            if limit is not None and usage is not None and limit < NO_LIMIT:
                headroom.append((limit - usage + (inactive or 0), limit))
    return headroom


def _cgroup_files(directory: Path, files: tuple[str, str, str]):
    """(limit, usage, inactive file bytes) of one cgroup directory; None for what is absent."""
    limit_file, usage_file, inactive_key = files

    def number(name):
        try:
            text = (directory / name).read_text().strip()
        except OSError:
            return None
        return NO_LIMIT if text == "max" else int(text)

    inactive = None
    try:
        for line in (directory / "memory.stat").read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == inactive_key:
                inactive = int(value)
    except OSError:
        pass
    return number(limit_file), number(usage_file), inactive


def _read_kib(path: str, field: str) -> int | None:
    """A `field: N kB` line of a /proc file, in bytes."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None
