"""Before a program over a crowd first runs: room for XLA's compiler, room for the program,
and a word where the crowd is large for the exact model.

    check_compiler_room("python -m gst_jax.predict")       # before anything compiles
    cost = compile_checked(program, args, config, slots, "a stream step over 320 slots")
    check_memory(cost, device, "1000 episodes at once", "use --chunk 100")

Before each compile, the memory left (`gst_jax.resources.available_memory`: the least of
MemAvailable, the cgroup limit's headroom and the address-space limit's) must hold XLA's
compiler too (`COMPILER_BYTES`); a process that cannot is refused in one line instead of
dying inside LLVM. On a CPU, a crowd above `CANDIDATES_PAY_ABOVE` people with the exact model
whose call is expected to take a second or more is announced in one line (a warning) before
its first call, with its expected time (`operation_count`) and XLA's estimate of its memory,
naming the option that makes it cheap, candidates= (`crowd_notice`). `make_predict` does all
this for its programs, `compile_checked` for any jitted program over a crowd (a stream's
step), and `check_memory` weighs any compiled program's estimate (navigation's episodes).
"""

from __future__ import annotations

import warnings

import jax

from gst_jax import resources
from gst_jax.config import ModelConfig
from gst_jax.errors import DataError
from gst_jax.predict.chunking import Chunking
from gst_jax.predict.cost import Estimate, devices_of, estimate
from gst_jax.resources import size

# What XLA's compiler itself takes beyond the process's memory while it compiles a predict
# program (its threads, LLVM's code sections); a process with less left died inside it
# (`std::bad_alloc`, "LLVM ERROR: Unable to allocate section memory!" or "pthread_create
# failed", a segfault), and with 32 MiB left even loading a compiled program from the
# persistent cache did. Measured as the address space that compiling and running a first
# predict (N = 8, K = 3) needed above the process's size (2-core VM, jaxlib 0.10.2, a limit
# set with setrlimit): 128-160 MiB at XLA's default optimisation level, 192-256 MiB at
# --xla_backend_optimization_level=0 (the test suite's); N = 300, K = 20 compiled its single
# vmap with 256 MiB left.
COMPILER_BYTES = 256 * 2 ** 20
# The candidate neighbourhood a large crowd is pointed to (docs/MODEL.md 2.4), and the crowd
# above which it predicts faster than the exact model: the paper's model, one sample, median
# call (2-core VM loaded by other work, CPU time): N = 24 14.7 / 11.2 ms, 32 25.5 / 18.7 ms
# (the wall-clock medians tie there), 48 70.7 / 24.0 ms, 64 163 / 41 ms, 300 15.9 / 0.29 s
# (docs/benchmarks.md, benchmarks/bench_neighbourhood.py).
SUGGESTED_CANDIDATES = 16
CANDIDATES_PAY_ABOVE = 32
# A call expected to take this long or more is worth a word (a choice, not a measurement;
# a robot's stream passes its model's step).
LONG_CALL_S = 1.0
# A predict program's arithmetic (`operation_count`) per second of one CPU core: 12.7-18.7 G
# per second of CPU time on the same VM over N = 16-300, exact and with 16 candidates; 12.7 G
# for the exact model at N = 300 (bench_neighbourhood.py's g_operations_per_cpu_s). The
# slowest, so that a call's expected time errs long.
CPU_OPERATIONS_PER_CORE_SECOND = 12.7e9


def check_compiler_room(what: str, device: jax.Device | None = None) -> None:
    """Refuse in one line (`DataError`) where the memory this process may still take on
    `device` (the default device) cannot hold XLA's compiler (`COMPILER_BYTES`): compiling
    there dies inside LLVM without a word. `what`: the work, for the message ("predicting 20
    samples of ...")."""
    available = resources.available_memory(device or jax.devices()[0])
    if available is not None and available[0] < COMPILER_BYTES:
        left, source = available
        raise DataError(f"{what}: XLA's compiler needs about {size(COMPILER_BYTES)} more "
                        f"than this process holds, and {size(left)} is left ({source}); "
                        "raise the limit")


def crowd_notice(config: ModelConfig, slots: int, cost: Estimate | Chunking,
                 device: jax.Device, what: str, slower_than_s: float | None = None
                 ) -> str | None:
    """The one line announcing a large crowd, or None: on a CPU, the exact model
    (`config.candidates` 0) over more than CANDIDATES_PAY_ABOVE people (slots: the program's
    pedestrian axis) where a call is expected to take `slower_than_s` (default LONG_CALL_S)
    or more. It gives what a call of the program about to run needs (`cost`: XLA's estimate
    of its memory; its time, its arithmetic at CPU_OPERATIONS_PER_CORE_SECOND on the cores
    this process may use, which other work slows) and the option that makes it cheap.
    `what`: the work ("predicting 20 samples of a scene of 300 people")."""
    if config.candidates or slots <= CANDIDATES_PAY_ABOVE or device.platform != "cpu":
        return None
    cores = resources.usable_cores()
    seconds = cost.operations / (CPU_OPERATIONS_PER_CORE_SECOND * cores)
    if seconds < (LONG_CALL_S if slower_than_s is None else slower_than_s):
        return None
    memory = "" if cost.bytes_needed is None else (
        f" and {size(cost.bytes_needed)} (XLA's estimate)")
    return (f"{what} with the exact model needs about {_seconds(seconds)} a call on {cores} "
            f"idle CPU core{'s' if cores > 1 else ''}{memory}; above "
            f"{CANDIDATES_PAY_ABOVE} people the candidate neighbourhood is faster: "
            f"candidates={SUGGESTED_CANDIDATES} (--candidates {SUGGESTED_CANDIDATES}; "
            "docs/MODEL.md 2.4)")


def compile_checked(program, args: tuple, config: ModelConfig | None, slots: int, what: str,
                    slower_than_s: float | None = None) -> Estimate:
    """Before the jitted `program` first runs on `args` over a crowd of `slots` people (a
    stream's step at a new capacity, a chunk of navigation episodes): refuse in one line
    where the memory left cannot hold the compiler; compile it (jit's cache keeps it: the
    call that follows does not compile again); refuse in one line where XLA's estimate of a
    call exceeds the memory available (the fix: fewer people, more memory, and for a gst_jax
    model candidates); where `config` is a gst_jax model's, warn
    in one line where the crowd is large for the exact model and a call is expected to take
    `slower_than_s` or more (`crowd_notice`; a robot's stream: its model's step_s). Returns
    the estimate. `what` names the work in those lines ("a stream step over 320 slots")."""
    leaves = [leaf for leaf in jax.tree.leaves(args) if hasattr(leaf, "shape")]
    devices = devices_of(leaves[0]) if leaves else jax.devices()[:1]
    check_compiler_room(what, devices[0])
    traced = program.trace(*args)
    cost = estimate(traced.lower().compile(), traced.jaxpr, devices)
    check_memory(cost, devices[0], what, "use fewer people or more memory" if config is None
                 else f"use fewer people, candidates={SUGGESTED_CANDIDATES} or more memory")
    if config is not None and (
            notice := crowd_notice(config, slots, cost, devices[0], what, slower_than_s)):
        warnings.warn(notice, stacklevel=2)
    return cost


def check_memory(cost: Estimate, device: jax.Device, what: str, fix: str) -> None:
    """Refuse in one line (`DataError`) where XLA's estimate of a call of a compiled program
    (`cost`) exceeds the memory this process may still take on `device`; `what` names the
    work, `fix` what to do ("use fewer people or more memory")."""
    available = resources.available_memory(device)
    if available is not None and cost.bytes_needed is not None and (
            cost.bytes_needed > available[0]):
        raise DataError(f"{what} needs {size(cost.bytes_needed)} (XLA's estimate); "
                        f"{size(available[0])} is available ({available[1]}); {fix}")


def _seconds(seconds: float) -> str:
    if seconds >= 120:
        return f"{seconds / 60:.0f} min"
    return f"{seconds:.2g} s" if seconds < 10 else f"{seconds:.0f} s"
