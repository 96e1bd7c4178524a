"""The host devices a process forces through XLA_FLAGS, and the XLA setting such a process
needs.

    keep_ynnpack_to_matrix_products()       # before jax starts its CPU backend

XLA:CPU in jaxlib 0.10 hands elementwise and reduction fusions to YNNPACK on some CPUs (AMD
EPYC), and one of them segfaulted in its transpose, seen only in a process that forces several
host devices (`--xla_force_host_platform_device_count=N`, N > 1: a sweep over 4 in
tests/test_parallel.py; docs/benchmarks.md, "Conditions"). Such a process keeps YNNPACK to its
matrix products; every other keeps all of its fusions, which the planner path needs (the
CrowdNav++ drop-in ran 2x slower without). XLA reads the flag when jax starts its CPU backend,
so it is set where the devices are put to use, before anything computes: when
`gst_jax.parallel` (the meshes over the devices, which every module that trains or evaluates
imports) is imported, and as a command starts (`gst_jax.cli.run`). A user's own setting of the
flag wins. `import gst_jax` changes no environment variable.

Imports nothing, not even jax: a command that computes nothing starts without it.
"""

from __future__ import annotations

import os
import re
from typing import MutableMapping

YNNPACK_FLAG = "--xla_cpu_experimental_ynn_fusion_type"


def forced_host_devices(xla_flags: str) -> int:
    """The host device count that XLA_FLAGS forces (1 where it forces none)."""
    counts = re.findall(r"--xla_force_host_platform_device_count=(\d+)", xla_flags)
    return int(counts[-1]) if counts else 1


def keep_ynnpack_to_matrix_products(environ: MutableMapping[str, str] | None = None) -> None:
    """Add `YNNPACK_FLAG=dot` to the XLA_FLAGS of `environ` (default: os.environ) where they
    force several host devices and do not set YNNPACK_FLAG already; leave them alone
    otherwise."""
    environ = os.environ if environ is None else environ
    flags = environ.get("XLA_FLAGS", "")
    if YNNPACK_FLAG not in flags and forced_host_devices(flags) > 1:
        environ["XLA_FLAGS"] = f"{flags} {YNNPACK_FLAG}=dot".strip()
