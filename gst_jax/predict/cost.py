"""What a compiled program needs: XLA's estimate of its memory and the count of its arithmetic.

    traced = program.trace(*args)
    cost = estimate(traced.lower().compile(), traced.jaxpr, devices_of(args[0]))
    cost.bytes_needed, cost.operations

XLA's estimate leaves out the scratch the CPU runtime takes while a call runs, so a CPU's
need is that estimate times CPU_RUNTIME_MARGIN; XLA's own count of operations takes every
loop's body once, so `operation_count` counts a jaxpr's arithmetic itself (a scan's body
times its length). `gst_jax.predict` chunks its samples by the first and announces a large
crowd's expected time by the second (`gst_jax.predict.checks`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax

# XLA's estimate leaves out the scratch the CPU runtime takes while a call runs, about one
# (N, N+1, N+1) float32 array per sample at once: measured up to 39 % more at N = 300, 11 % at
# N = 200 (benchmarks/bench_memory.py), so a CPU's need is taken as the estimate times this.
CPU_RUNTIME_MARGIN = 1.4


class Estimate(NamedTuple):
    """What a compiled program needs: `Chunking`'s xla_bytes, bytes_needed and operations."""

    xla_bytes: int | None
    bytes_needed: int | None
    operations: float


def devices_of(array) -> list[jax.Device]:
    """The devices holding `array`, by id (the default device for a host array)."""
    devices = getattr(getattr(array, "sharding", None), "device_set", None)
    return sorted(devices, key=lambda d: d.id) if devices else jax.devices()[:1]


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
