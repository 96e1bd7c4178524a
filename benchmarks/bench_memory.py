"""Peak memory of `make_predict` on one large crowd: one vmap over the samples, and chunked.

    python benchmarks/bench_memory.py --sizes 100 200 300 --samples 20
    python benchmarks/bench_memory.py --sizes 300 --address-space-gib 3

Each case is a fresh child process, whose peak RSS the kernel reports (`wait4`): the paper's
model (ModelConfig() defaults; the shipped eth_d weights, as a user loads them) predicts K
samples of one scene of N random walkers, without the graphs (as evaluation and prediction
files do). `whole` is the old program, one vmap over all K samples (forced: an unbounded
budget, and no look at the memory available); `chunked` is the default budget
(`gst_jax.predict.DEFAULT_MEMORY_BUDGET`). Reported: the chunking chosen, XLA's estimate and
the need taken from it (with the CPU runtime's margin), the seconds spent choosing and
compiling, one call after that, and the peak RSS of the whole process (interpreter, jax,
weights and compiler included). `--address-space-gib` runs the children under that
RLIMIT_AS (`ulimit -v`; not a cgroup limit): a case that cannot fit must end with one line,
not be killed.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

from common import print_table, record

# The budget of each mode (None: the default). `whole` also ignores the memory available, as
# the old program did.
MODES = {"whole": 2 ** 50, "chunked": None}


def one_case(num_pedestrians: int, num_samples: int, budget: int | None) -> dict:
    """In this process: choose and compile, then time one call; the figures of one case."""
    import jax
    import numpy as np

    from gst_jax import load_pretrained, make_batch, resources
    from gst_jax.config import ModelConfig
    from gst_jax.errors import DataError
    from gst_jax.predict import DEFAULT_MEMORY_BUDGET, make_predict

    if budget == MODES["whole"]:
        resources.available_memory = lambda device: None

    config, params = load_pretrained("eth_d")
    assert config == ModelConfig(), "eth_d is the paper's model"
    rng = np.random.default_rng(num_pedestrians)
    xy = np.cumsum(rng.normal(0.0, 0.3, (1, config.obs_len, num_pedestrians, 2)), axis=1)
    batch = make_batch(xy + rng.uniform(-15, 15, (1, 1, num_pedestrians, 2)))
    predict = make_predict(config, num_samples, with_graph=False,
                           memory_budget_bytes=budget or DEFAULT_MEMORY_BUDGET)
    key = jax.random.key(1)
    start = time.perf_counter()
    try:
        chunking = predict.chunking(params, key, batch)
    except DataError as error:
        return {"refused": str(error)}
    chosen = time.perf_counter()
    positions = np.asarray(predict(params, key, batch).positions)
    return {"samples_at_once": chunking.samples_at_once,
            "observed_steps_at_once": chunking.observed_steps_at_once or config.obs_len,
            "xla_estimate_gib": chunking.xla_bytes / 2 ** 30,
            "needed_gib": chunking.bytes_needed / 2 ** 30,
            "choose_compile_s": chosen - start, "call_s": time.perf_counter() - chosen,
            "finite": bool(np.isfinite(positions).any())}


def run_child(num_pedestrians: int, num_samples: int, mode: str,
              address_space_gib: float | None) -> dict:
    """One case in a fresh interpreter; its peak RSS from the kernel (`wait4`), which also
    holds for a child that was killed."""
    command = [sys.executable, __file__, "--child", str(num_pedestrians), str(num_samples),
               str(MODES[mode] or 0), str(address_space_gib or 0)]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        child = subprocess.Popen(command, stdout=out, stderr=err, text=True)
        _, status, usage = os.wait4(child.pid, 0)
        child.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        lines, errors = out.read().strip().splitlines(), err.read().strip().splitlines()
    if child.returncode == 0 and lines:
        result = json.loads(lines[-1])
    else:
        last = errors[-1] if errors else "(nothing on stderr)"
        result = {"refused": f"exit {child.returncode}: {last[:200]}"}
    result["peak_rss_gib"] = usage.ru_maxrss / 2 ** 20
    return result


def main() -> None:
    if sys.argv[1:2] == ["--child"]:
        n, k, budget = (int(a) for a in sys.argv[2:5])
        if address_space := float((sys.argv[5:] or [0])[0]) * 2 ** 30:
            # Set here, before jax starts its threads (a preexec_fn would fork them).
            resource.setrlimit(resource.RLIMIT_AS, (int(address_space), int(address_space)))
        print(json.dumps(one_case(n, k, budget or None)), flush=True)
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="*", type=int, default=[100, 200, 300])
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--modes", nargs="*", default=list(MODES), choices=MODES)
    parser.add_argument("--address-space-gib", type=float, default=None)
    args = parser.parse_args()
    rows = []
    for n in args.sizes:
        for mode in args.modes:
            result = run_child(n, args.samples, mode, args.address_space_gib)
            rows.append(record("memory", workload=f"N={n}", samples=args.samples, mode=mode,
                               address_space_gib=args.address_space_gib, **result))
            print(json.dumps(rows[-1]), flush=True)
    print_table(rows, ["workload", "samples", "mode", "samples_at_once",
                       "observed_steps_at_once", "xla_estimate_gib", "needed_gib", "peak_rss_gib",
                       "choose_compile_s", "call_s", "refused"])


if __name__ == "__main__":
    main()
