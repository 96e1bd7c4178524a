"""Data-parallel training over 1 -> 2 -> 4 devices: one epoch's wall time per device count.

    python benchmarks/bench_scaling.py --scene eth --devices 1,2,4

Each device count runs in its own process. On a CPU machine the devices are forced
(`--xla_force_host_platform_device_count`): they share the same cores, so this measures the
cost of the partitioned program, not a speed-up; on a machine with several GPUs the real
devices are used. The first epoch compiles every program (timed apart); the second is timed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

from common import peak_rss_gib, print_table, record


def worker(scene: str, count: int, max_windows: int) -> dict:
    import jax

    from gst_jax import data, parallel
    from gst_jax.config import DataConfig, ModelConfig, TrainConfig
    from gst_jax.training.state import create_train_state, hparams_for_epoch, step_key
    from gst_jax.training.step import make_train_step

    config, train_config = ModelConfig(), TrainConfig()
    train_set = data.load_split(DataConfig(scene=scene), "train")
    if max_windows:
        train_set = train_set.subset(range(min(max_windows, len(train_set))))
    devices = parallel.devices(count) if count > 1 else None
    step = make_train_step(config, devices=devices)
    state = step.place(create_train_state(config, jax.random.key(0)))
    hparams = step.place(hparams_for_epoch(config, train_config, 1))
    times = []
    for epoch in (1, 2):
        start = time.perf_counter()
        for index, packed in enumerate(data.training_batches(
                train_set, batch_size=16, seed=0, epoch=epoch,
                slots_multiple=step.slots_multiple)):
            state, metrics = step(state, step.place(step_key(0, epoch, index)), packed, hparams)
        jax.block_until_ready(metrics["loss"])
        times.append(time.perf_counter() - start)
    return {"devices": count, "platform": jax.devices()[0].platform, "windows": len(train_set),
            "first_epoch_s": times[0], "epoch_s": times[1], "peak_rss_gib": peak_rss_gib()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="eth", help="dataset (default: eth)")
    parser.add_argument("--devices", default="1,2,4", help="device counts (default: 1,2,4)")
    parser.add_argument("--max-windows", type=int, default=0,
                        help="train on the first k windows only (default: all)")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker is not None:
        print(json.dumps(worker(args.scene, args.worker, args.max_windows)))
        return

    rows = []
    for count in [int(c) for c in args.devices.split(",")]:
        environment = dict(os.environ)
        if not _has_accelerators():
            environment["XLA_FLAGS"] = (environment.get("XLA_FLAGS", "") +
                                        f" --xla_force_host_platform_device_count={count}")
        result = subprocess.run([sys.executable, __file__, "--scene", args.scene,
                                 "--max-windows", str(args.max_windows), "--worker", str(count)],
                                capture_output=True, text=True, env=environment)
        if result.returncode:
            sys.exit(result.stderr[-2000:])
        row = json.loads(result.stdout.strip().splitlines()[-1])
        row["speed_up"] = rows[0]["epoch_s"] / row["epoch_s"] if rows else 1.0
        rows.append(row)
        record("scaling", scene=args.scene, **row)
    print_table(rows, ["devices", "platform", "windows", "first_epoch_s", "epoch_s", "speed_up",
                       "peak_rss_gib"])


def _has_accelerators() -> bool:
    """Asked in a process of its own: this one must not hold the GPUs its workers use."""
    backend = subprocess.run([sys.executable, "-c", "import jax; print(jax.default_backend())"],
                             capture_output=True, text=True).stdout.strip()
    return backend not in ("", "cpu")


if __name__ == "__main__":
    main()
