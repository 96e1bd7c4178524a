"""One prediction of a large crowd: the exact model against a candidate neighbourhood.

    python benchmarks/bench_neighbourhood.py --sizes 50 300 --candidates 0 16 --rounds 3

The paper's model (ModelConfig() defaults; the shipped eth_d weights, or another shipped model
with `--model`) predicts one sample of one scene of N random walkers without the graphs
(`make_predict(config, 1, with_graph=False)`),
exactly (`candidates` 0) or with each target's k nearest people as its only candidates
(`ModelConfig.candidates`, docs/MODEL.md 2.4), with the same parameters. Each case runs in a
fresh child process: it compiles (and chooses its chunking), then times `--calls` calls; the
peak RSS of the whole process (interpreter, jax, weights and compiler included) is the
kernel's (`wait4`). The cases are interleaved round by round, so that a machine whose load
changes slows every case alike; reported: the median over every timed call of every round,
and the largest peak RSS. Beside the wall time, the process's CPU time per call (all its
threads): on a machine shared with other work, the wall time includes the time the call
waited for a core. Also what `make_predict` estimates the program needs (`Chunking`: XLA's
estimate of its memory, its arithmetic counted on the jaxpr) and that arithmetic per second
of CPU time, the rate behind `gst_jax.predict.CPU_OPERATIONS_PER_CORE_SECOND`. Last, the
sizes at which the candidates' median call is the faster (`CANDIDATES_PAY_ABOVE`).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from common import print_table, record


def one_case(model: str, num_pedestrians: int, candidates: int, calls: int) -> dict:
    """In this process: compile, then time `calls` calls of one case."""
    import dataclasses

    import jax
    import numpy as np

    from gst_jax import load_pretrained, make_batch
    from gst_jax.config import ModelConfig
    from gst_jax.predict import make_predict

    config, params = load_pretrained(model)
    assert model != "eth_d" or config == ModelConfig(), "eth_d is the paper's model"
    config = dataclasses.replace(config, candidates=candidates)
    rng = np.random.default_rng(num_pedestrians)
    xy = np.cumsum(rng.normal(0.0, 0.3, (1, config.obs_len, num_pedestrians, 2)), axis=1)
    batch = make_batch(xy + rng.uniform(-15, 15, (1, 1, num_pedestrians, 2)))
    predict = make_predict(config, 1, with_graph=False)
    start = time.perf_counter()
    predict(params, jax.random.key(0), batch).positions.block_until_ready()
    compile_s = time.perf_counter() - start
    seconds, cpu_seconds = [], []
    for call in range(calls):
        start, cpu_start = time.perf_counter(), time.process_time()
        predict(params, jax.random.key(call + 1), batch).positions.block_until_ready()
        seconds.append(time.perf_counter() - start)
        cpu_seconds.append(time.process_time() - cpu_start)
    chunking = predict.chunking(params, jax.random.key(0), batch)
    return {"compile_s": compile_s, "call_ms": [1e3 * s for s in seconds],
            "cpu_ms": [1e3 * s for s in cpu_seconds], "operations": chunking.operations,
            "xla_bytes_needed": chunking.bytes_needed}


def run_child(model: str, num_pedestrians: int, candidates: int, calls: int) -> dict:
    """One case in a fresh interpreter; its peak RSS from the kernel (`wait4`)."""
    command = [sys.executable, __file__, "--child", model, str(num_pedestrians),
               str(candidates), str(calls)]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        child = subprocess.Popen(command, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(child.pid, 0)
        out.seek(0)
        err.seek(0)
        lines, errors = out.read().strip().splitlines(), err.read().strip().splitlines()
    if os.waitstatus_to_exitcode(status) != 0 or not lines:
        raise RuntimeError(f"N = {num_pedestrians}, candidates {candidates}: "
                           f"{errors[-1] if errors else 'no output'}")
    return {**json.loads(lines[-1]), "peak_rss_gib": usage.ru_maxrss / 2 ** 20}


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        n, k, calls = (int(a) for a in sys.argv[3:6])
        print(json.dumps(one_case(sys.argv[2], n, k, calls)), flush=True)
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="*", type=int, default=[50, 300])
    parser.add_argument("--candidates", nargs="*", type=int, default=[0, 16],
                        help="k per case; 0 = the exact model")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--calls", type=int, default=5, help="timed calls per child")
    parser.add_argument("--model", default="eth_d", help="a shipped model (default: eth_d)")
    args = parser.parse_args()
    cases = [(n, k) for n in args.sizes for k in args.candidates]
    runs = {case: [] for case in cases}
    for round_ in range(args.rounds):
        for n, k in cases:
            runs[(n, k)].append(run_child(args.model, n, k, args.calls))
            print(f"round {round_ + 1}: N = {n}, candidates {k}: "
                  f"{statistics.median(runs[(n, k)][-1]['call_ms']):.1f} ms", file=sys.stderr,
                  flush=True)
    rows = []
    for (n, k), results in runs.items():
        calls = [ms for result in results for ms in result["call_ms"]]
        cpu = [ms for result in results for ms in result["cpu_ms"]]
        operations, needed = results[0]["operations"], results[0]["xla_bytes_needed"]
        rows.append(record("neighbourhood", workload=f"N={n}", model=args.model, samples=1,
                           candidates=k, rounds=args.rounds, calls=len(calls),
                           median_call_ms=statistics.median(calls),
                           min_call_ms=min(calls), max_call_ms=max(calls),
                           median_cpu_ms=statistics.median(cpu),
                           compile_s=statistics.median(r["compile_s"] for r in results),
                           peak_rss_gib=max(r["peak_rss_gib"] for r in results),
                           xla_gib=needed and needed / 2 ** 30,
                           g_operations=operations / 1e9,
                           g_operations_per_cpu_s=operations / 1e6 / statistics.median(cpu)))
    print_table(rows, ["workload", "candidates", "calls", "median_call_ms", "min_call_ms",
                       "max_call_ms", "median_cpu_ms", "compile_s", "peak_rss_gib", "xla_gib",
                       "g_operations", "g_operations_per_cpu_s"])
    for measure in ("call_ms", "cpu_ms"):
        median = {(n, k): statistics.median(ms for r in results for ms in r[measure])
                  for (n, k), results in runs.items()}
        for k in (k for k in args.candidates if k > 0 and 0 in args.candidates):
            faster = [n for n in args.sizes if median[(n, k)] < median[(n, 0)]]
            print(f"candidates {k}: faster than the exact model ({measure}, median) at N = "
                  f"{', '.join(map(str, faster)) or 'none of these sizes'}")


if __name__ == "__main__":
    main()
