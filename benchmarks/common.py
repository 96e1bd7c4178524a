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


def flops_of(compiled) -> float:
    """FLOPs of one call of a compiled jax function, from XLA's cost analysis."""
    analysis = compiled.cost_analysis()
    analysis = analysis[0] if isinstance(analysis, (list, tuple)) else analysis
    return float(analysis.get("flops", 0.0))


def machine() -> str:
    device = jax.devices()[0]
    return f"{device.platform}:{getattr(device, 'device_kind', '')} ({platform.processor() or platform.machine()}, {jax.local_device_count()} device(s))"


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
