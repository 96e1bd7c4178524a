"""Shared helpers of the benchmarks: peak RSS, cost analysis, JSON-lines results, tables."""

from __future__ import annotations

import json
import platform
import resource
import time
from pathlib import Path

import jax

RESULTS = Path(__file__).parent / "results.jsonl"


def peak_rss_gib() -> float:
    """Peak resident memory of this process so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


def matmul_flops(function, *args) -> float:
    """FLOPs of the matrix products (dot_general, 2 per multiply-add) of one call, counted on
    its jaxpr: scan bodies times their length, rematerialised forwards included.

    XLA's cost analysis counts a while loop's body once, so for our rollout (11 prediction
    steps in a scan) it undercounts; earlier tables that used it did too.
    """
    return _jaxpr_flops(jax.make_jaxpr(function)(*args).jaxpr)


def _jaxpr_flops(jaxpr) -> float:
    total = 0.0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "dot_general":
            (lhs_contract, _), (lhs_batch, _) = eqn.params["dimension_numbers"]
            lhs, rhs = (v.aval.shape for v in eqn.invars)
            out = eqn.outvars[0].aval.shape
            contracted = 1
            for axis in lhs_contract:
                contracted *= lhs[axis]
            size = 1
            for dim in out:
                size *= dim
            total += 2.0 * size * contracted
            continue
        repeat = eqn.params.get("length", 1) if eqn.primitive.name == "scan" else 1
        for param in eqn.params.values():
            for sub in (param if isinstance(param, (list, tuple)) else [param]):
                inner = getattr(sub, "jaxpr", None)
                if inner is not None and hasattr(inner, "eqns"):
                    total += repeat * _jaxpr_flops(inner)
                elif hasattr(sub, "eqns"):
                    total += repeat * _jaxpr_flops(sub)
    return total


def machine() -> str:
    device = jax.devices()[0]
    processor = platform.processor() or platform.machine()
    return (f"{device.platform}:{getattr(device, 'device_kind', '')} "
            f"({processor}, {jax.local_device_count()} device(s))")


def record(benchmark: str, **fields) -> dict:
    """Append one result line to benchmarks/results.jsonl and return it."""
    line = {"benchmark": benchmark, "time": time.strftime("%Y-%m-%d %H:%M:%S"),
            "machine": machine(), "jax": jax.__version__, **fields}
    with RESULTS.open("a") as f:
        f.write(json.dumps(line) + "\n")
    return line


def print_table(rows: list[dict], columns: list[str]) -> None:
    widths = [max(len(c), *(len(_fmt(r.get(c))) for r in rows)) for c in columns]
    print("  ".join(c.ljust(w) for c, w in zip(columns, widths)))
    for row in rows:
        print("  ".join(_fmt(row.get(c)).ljust(w) for c, w in zip(columns, widths)))


def _fmt(value) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "-" if value is None else str(value)
