"""How a prediction's program computes within the memory it may use: its samples in chunks.

The edge selector attends over (N + 1)^2 neighbour pairs for each of N targets, so a call
grows as K N^3 (N = 300, K = 20: 9.3 GiB, 6.2 GiB of it one buffer). Before a batch shape
first runs, XLA's estimate of its compiled program (`gst_jax.predict.cost`) is compared with
a budget and with the memory this process may still take (`gst_jax.resources`); a program
over either computes its samples in chunks (`lax.map`, a vmap within each) and the observed
steps one at a time, with the same keys and so the same samples; one that cannot fit even
one sample at a time is refused in one line (`DataError`) before anything is allocated
(docs/scaling.md). `choose` makes that choice; `make_predict` builds and runs the programs.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from gst_jax.errors import DataError
from gst_jax.resources import size

# What one call's program may use by default, chunking its samples to stay within it:
# N = 300, K = 20 then runs 2 samples at a time (1.1 GiB, 1.6 GiB peak for the process) instead
# of all 20 (8.9 GiB); up to N = 128 at K = 20 (0.7 GiB) it keeps the single vmap over samples.
DEFAULT_MEMORY_BUDGET = 3 * 2 ** 29
# A chunking is chosen this far below the target, so that the first one measured fits.
CHUNKING_SLACK = 0.95


@dataclasses.dataclass(frozen=True)
class Chunking:
    """How the program of one batch shape computes, and what XLA says it needs.

    samples_at_once: samples vmapped together, looped over chunks (K: one vmap).
    observed_steps_at_once: observed steps per edge-selector call (None: all at once).
    xla_bytes: temporaries + arguments + outputs of the compiled program, over every device
      of a CPU (they share its memory); None where XLA does not say.
    bytes_needed: what a call takes: xla_bytes, times CPU_RUNTIME_MARGIN on a CPU.
    operations: the program's arithmetic (`operation_count`), what its time grows with.
    """

    samples_at_once: int
    observed_steps_at_once: int | None
    xla_bytes: int | None
    bytes_needed: int | None
    operations: float = 0.0


def choose(measure: Callable[[int, int | None], Chunking], num_samples: int, budget: int,
           available: tuple[int, str] | None, what: str) -> Chunking:
    """The fastest chunking within `budget` and the memory `available` (bytes, where that
    figure comes from; None: unknown): the single vmap over `num_samples` if it fits, else as
    many samples at once as fit, observing step by step. `measure(samples_at_once,
    observed_steps_at_once)` compiles a chunking's program and reads XLA's estimate of it;
    `what` names the work in the refusal ("predicting 20 samples of a scene of 300 people")."""
    target = budget if available is None else min(budget, available[0])
    whole = measure(num_samples, None)
    if whole.bytes_needed is None or whole.bytes_needed <= target:
        return whole
    least = measure(1, 1)
    least_bytes = _bytes_needed(least)
    if available is not None and least_bytes > available[0]:
        raise DataError(f"{what} needs {size(least_bytes)} at least (one sample at a "
                        f"time); {size(available[0])} is available ({available[1]}); use "
                        "fewer people per scene or more memory")
    # The need grows linearly with the samples at once (XLA: 0.16 + 0.31 c GiB at
    # N = 300); the slope through `whole` overestimates it where the observed steps at
    # once dominate, and every candidate is measured before it is chosen.
    per_sample = (whole.bytes_needed - least_bytes) / max(num_samples - 1, 1)
    while True:
        room = CHUNKING_SLACK * target - least_bytes
        chunk = min(num_samples, 1 + int(room // max(per_sample, 1)))
        if chunk <= 1:
            return least
        candidate = measure(chunk, 1)
        candidate_bytes = _bytes_needed(candidate)
        if candidate_bytes <= target:
            return candidate
        per_sample = (candidate_bytes - least_bytes) / (chunk - 1)


def _bytes_needed(chunking: Chunking) -> int:
    """A smaller chunking's need, known where the whole program's is (the same compiler)."""
    assert chunking.bytes_needed is not None, "XLA estimated the whole program, not this one"
    return chunking.bytes_needed
