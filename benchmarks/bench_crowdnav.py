"""A planner's calls: gst_jax's CrowdNav++ drop-in beside CrowdNav++'s own predictor.

    python benchmarks/bench_crowdnav.py                          # ours only
    python benchmarks/bench_crowdnav.py --crowdnav PATH          # and CrowdNav++'s (torch)

One batched mean-mode call for n_env environments x 20 humans, 5 observed and 5 predicted
steps, with the `..._seed1000/sj` checkpoint (read from tests/fixtures/crowdnav_parity.npz,
which holds its weights), on the same inputs for both: calls per second after compilation
(the median of --calls calls, each one from numpy inputs to numpy outputs). CrowdNav++'s
runs with torch's threads set to --torch-threads (its interface as CrowdNav++ calls it, from
a checkout at PATH; needs torch). The fraction of peak is of ours: its matmul FLOPs per
second over the measured dense-matmul peak (bench_peak.py).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax
import numpy as np

from bench_peak import measure_peak_gflops
from common import matmul_flops, print_table, record
from gst_jax import crowdnav
from gst_jax.safe_pickle import read_args

FIXTURE = Path(__file__).parents[1] / "tests" / "fixtures" / "crowdnav_parity.npz"
CHECKPOINT = ("gst_updated/results/100-gumbel_social_transformer-faster_lstm-lr_0.001-"
              "init_temp_0.5-edge_head_0-ebd_64-snl_1-snh_8-seed_1000/sj")


def inputs(num_env: int, num_humans: int = 20, obs_len: int = 5, seed: int = 0):
    """Humans walking 0.25 s steps; a quarter of them enter view during the observation."""
    rng = np.random.default_rng(seed)
    start = rng.uniform(-5, 5, (num_env, num_humans, 1, 2))
    velocity = rng.normal(0, 0.8, (num_env, num_humans, 1, 2))
    traj = start + velocity * 0.25 * np.arange(obs_len)[:, None]
    mask = np.ones((num_env, num_humans, obs_len, 1))
    mask[:, : num_humans // 4, : obs_len // 2] = 0
    return np.where(mask > 0, traj, -999.0).astype(np.float32), mask.astype(np.float32)


def median_seconds(call, calls: int) -> float:
    call()                                               # compile / warm up
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def ours() -> crowdnav.Predictor:
    fixture = np.load(FIXTURE)
    prefix = "seed1000/state_dict/"
    state_dict = {k[len(prefix):]: fixture[k] for k in fixture.files if k.startswith(prefix)}
    return crowdnav.from_state_dict(state_dict, json.loads(str(fixture["seed1000/args"])))


def crowdnav_interface(path: Path, num_env: int, threads: int):
    """CrowdNav++'s own predictor, as CrowdNav++ builds it (its code, from its checkout)."""
    sys.path.insert(0, str(path.absolute()))
    import torch
    from gst_updated.scripts.wrapper.crowd_nav_interface_parallel import (
        CrowdNavPredInterfaceMultiEnv,
    )
    torch.set_num_threads(threads)
    load_path = path / CHECKPOINT
    # Its args.pickle read without running what it names; its own code reads the .pt with
    # torch's weights-only loading.
    args = argparse.Namespace(**read_args(load_path / "checkpoint" / "args.pickle"))
    multiarray = np._core.multiarray if hasattr(np, "_core") else np.core.multiarray
    allowed = [(multiarray.scalar, "numpy.core.multiarray.scalar"), np.dtype,
               type(np.dtype(np.float32)), type(np.dtype(np.float64))]
    with torch.serialization.safe_globals(allowed):
        model = CrowdNavPredInterfaceMultiEnv(str(load_path), torch.device("cpu"), args, num_env)

    def call(traj, mask):
        with torch.no_grad():
            out, out_mask = model.forward(torch.from_numpy(traj), torch.from_numpy(mask),
                                          sampling=False)
        return out.numpy(), out_mask.numpy()
    return call


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--envs", nargs="*", type=int, default=[1, 16, 64])
    parser.add_argument("--calls", type=int, default=50)
    parser.add_argument("--crowdnav", type=Path, default=None,
                        help="a CrowdNav++ checkout, to time its predictor beside ours")
    parser.add_argument("--torch-threads", type=int, default=2)
    args = parser.parse_args()

    predictor = ours()
    peak = measure_peak_gflops()
    rows = []
    for num_env in args.envs:
        traj, mask = inputs(num_env)
        ours_s = median_seconds(lambda: [np.asarray(a) for a in predictor(traj, mask)],
                                args.calls)
        flops = matmul_flops(lambda p: crowdnav.predict(p, predictor.config, traj, mask)[0],
                             predictor.params)
        row = dict(workload=f"n_env={num_env} x 20 humans", ms_per_call=1e3 * ours_s,
                   calls_per_s=1 / ours_s, fraction_of_peak=flops / ours_s / 1e9 / peak)
        if args.crowdnav is not None:
            theirs = crowdnav_interface(args.crowdnav, num_env, args.torch_threads)
            theirs_s = median_seconds(lambda: theirs(traj, mask), args.calls)
            row.update(crowdnav_ms_per_call=1e3 * theirs_s, speedup=theirs_s / ours_s)
        rows.append(record("crowdnav", **row))
    print(f"peak (matmul): {peak:.0f} GFLOP/s; {jax.devices()[0].platform}")
    print_table(rows, ["workload", "ms_per_call", "calls_per_s", "crowdnav_ms_per_call",
                       "speedup", "fraction_of_peak"])


if __name__ == "__main__":
    main()
