"""The program whose YNNPACK fusion segfaulted (jaxlib 0.10.2, XLA:CPU, AMD EPYC), for a report
upstream: a sweep of four members (n in {1, 2} x 2 seeds) of a one-layer GST on hotel's first
windows, trained one epoch and evaluated, split over forced host devices.

    XLA_FLAGS="--xla_force_host_platform_device_count=4 \
    --xla_cpu_experimental_ynn_fusion_type=dot,eltwise,reduce" \
        python3 benchmarks/ynnpack_sweep_repro.py 4

On the AMD EPYC VM of 2026-12-03 it exited 139 every time with elementwise or reduction fusions
given to YNNPACK (gdb: `slinky::fuse_contiguous_dims` under `YnnFusionThunk`, on an XLA worker
thread) and ran with `=dot` or `=`. On the VM of 2026-12-04 (family 25 model 17) it runs with
every setting (docs/benchmarks.md, "Conditions"). Setting the YNNPACK flag yourself keeps
gst_jax.parallel from adding `=dot` (gst_jax/host_devices.py). Prints the members' AOE; exit
0 = no crash.
"""

import sys
import tempfile

import jax

from gst_jax import parallel
from gst_jax.config import DataConfig, ModelConfig, TrainConfig
from gst_jax.training import members as sweep_members, sweep

count = int(sys.argv[1]) if len(sys.argv) > 1 else 4
if jax.device_count() != count:
    raise SystemExit(f"{jax.device_count()} devices: run with "
                     f"XLA_FLAGS=--xla_force_host_platform_device_count={count}")
devices = parallel.devices(count) if count > 1 else None
config, hotel = ModelConfig(encoder_layers=1), DataConfig(scene="hotel")
members = sweep_members.plan_members([1, 2], "partial", [3, 4])
results = sweep.fit_sweep(sweep_members.sweep_model_config(config, members), hotel,
                          TrainConfig(epochs=1, batch_size=4, seed=3, max_train_windows=8),
                          members, f"{tempfile.mkdtemp()}/sweep", eval_samples=2,
                          max_eval_windows=4, devices=devices)
print("ok", [round(r["aoe"], 4) for r in results["members"]])
