"""Data parallelism with `jax.sharding`: one mesh axis, "data", over the devices.

Training splits the scenes of every micro-batch over the devices, with parameters and
optimiser state replicated: XLA partitions the jitted step and reduces the gradients inside
it (no hand-written collectives). A sweep splits its members instead, evaluation the scenes
of each batch. Each window's random draws depend on its own key and coordinates only
(`gst_jax.noise`), so the results are those of one device up to the order of the sums.

Several processes (one per machine, or per GPU) join with `jax.distributed.initialize`
(`join_processes`); their devices form one mesh, and each process feeds only the shards of
its own devices (`jax.make_array_from_callback`) from the same host data.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gst_jax.errors import DeviceError
from gst_jax.host_devices import keep_ynnpack_to_matrix_products

DATA = "data"

# A process that forces several host devices keeps XLA's YNNPACK to its matrix products
# (`gst_jax.host_devices`: one of its other fusions segfaulted there). Set on import, before
# anything computes on the devices this module spreads work over.
keep_ynnpack_to_matrix_products()


@dataclasses.dataclass(frozen=True)
class Devices:
    """The devices a computation is spread over: a one-axis mesh."""

    mesh: Mesh

    @property
    def count(self) -> int:
        return self.mesh.size

    def split(self, tree: Any) -> Any:
        """Host arrays -> global arrays split along their leading axis (its size a multiple
        of `count`); each process supplies only its own devices' shards."""
        return self._put(tree, PartitionSpec(DATA))

    def replicate(self, tree: Any) -> Any:
        """Host or device arrays -> global arrays with a full copy on every device."""
        return self._put(tree, PartitionSpec())

    def _put(self, tree: Any, spec: PartitionSpec) -> Any:
        sharding = NamedSharding(self.mesh, spec)

        def put(leaf):
            if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype,
                                                                     jax.dtypes.prng_key):
                data = np.asarray(jax.random.key_data(leaf))
                return jax.random.wrap_key_data(put(data), impl=jax.random.key_impl(leaf))
            value = np.asarray(leaf)
            return jax.make_array_from_callback(value.shape, sharding,
                                                lambda index: value[index])

        return jax.tree.map(put, tree)

    def gather(self, tree: Any) -> Any:
        """Global arrays -> numpy arrays of their full value, on every process."""
        if jax.process_count() == 1:
            return jax.tree.map(np.asarray, tree)
        return multihost_utils.process_allgather(tree, tiled=True)


def devices(count: int | None = None) -> Devices:
    """A mesh over every device of every process (the default), or the first `count` of
    them (one process only)."""
    available = jax.devices()
    if count is not None:
        if not 1 <= count <= len(available):
            raise DeviceError(f"--devices {count}: this machine has {len(available)} "
                              f"{available[0].platform.upper()} device(s)")
        if jax.process_count() > 1 and count != len(available):
            raise DeviceError("--devices limits one process; with several processes every "
                              "device of every process is used")
        available = available[:count]
    return Devices(Mesh(np.array(available), (DATA,)))


def join_processes(coordinator: str | None = None, num_processes: int | None = None,
                   process_id: int | None = None) -> None:
    """`jax.distributed.initialize` from the flags, or from the cluster's environment
    (Slurm, Open MPI, ...) when they are None. On CPUs the processes exchange gradients
    through gloo (the setting does nothing on GPUs). Call it before any computation."""
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id)
