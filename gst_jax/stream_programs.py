"""A stream step's compiled programs, one per capacity, and each step run within a deadline:
how a stream's slots (`gst_jax.stream_slots.Slots`) run the model.

A capacity's program is compiled before its first step, checked (`gst_jax.predict.
compile_checked`: its memory for every predictor, a large crowd for a gst_jax model): at that
step, the loop waiting (without a deadline, and for the first program: `Programs.inline`), or
else in the background, one compile at a time for all of a process's streams
(`compile_behind`, taken by `collect`). With a deadline, each step runs in a thread of the
stream's and is waited for until then (`run_in_time`): a step past it runs on, its outputs
unused (`Programs.busy`). Compiles with their seconds and overruns (steps longer than the
model's period) are logged (logger "gst_jax.stream").
"""

from __future__ import annotations

import functools
import logging
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from time import perf_counter
from typing import Any, Callable

import jax
import numpy as np

from gst_jax.adaptation import Adaptation
from gst_jax.conformal import Regions
from gst_jax.errors import DataError
from gst_jax.model import Params
from gst_jax.predict import compile_checked
from gst_jax.predictors import ConstantVelocity, Predictor, Standing
from gst_jax.stream_core import Frame, Gate, StreamModel, StreamState, make_step

logger = logging.getLogger("gst_jax.stream")


@functools.lru_cache(maxsize=16)
def _jitted_step(model: Predictor, regions: Regions | None, gate: Gate | None,
                 adaptation: Adaptation | None = None, step_s: float | None = None
                 ) -> Callable:
    """`make_step` jitted once per (model, regions, gate, adaptation, step_s), with the
    key of the step folded in: streams of one model, one after another (a recorded scene's
    files), share its compiled programs. Its `idle` empty steps (after a gap in the frames)
    come before the step, which folds in the index it reaches."""
    step = make_step(model, regions, gate=gate, step_s=step_s, adaptation=adaptation)

    def host_step(params: Params, state: StreamState, frame: Frame, key: jax.Array,
                  index: jax.Array, idle: jax.Array):
        return step(params, state, frame, jax.random.fold_in(key, index + idle), idle)
    return jax.jit(host_step)


class Programs:
    """One stream's compiled steps (the module docstring), called with the jitted step's
    arguments (params, state, frame, key, index, idle). compiled: each capacity compiled, with
    its compile's seconds; compiling: the background compile, (capacity, its future), or None;
    failed: the capacities whose compile failed; overruns: the steps that took longer than
    step_s, the model's period. deadline_s: how long a step is waited for; None: to its end."""

    def __init__(self, model: StreamModel | ConstantVelocity | Standing,
                 regions: Regions | None, gate: Gate | None, adaptation: Adaptation | None,
                 step_s: float, deadline_s: float | None):
        self._step = _jitted_step(model, regions, gate, adaptation, step_s)
        # The model config whose crowd `compile_checked` announces before a capacity's first
        # step (issue 78: a gst_jax model's; None for CrowdNav++'s and predictors without one).
        self._config = (model.config if isinstance(model, StreamModel)
                        and model.convention == "gst" else None)
        self.step_s, self.deadline_s = step_s, deadline_s
        self.compiled: dict[int, float] = {}
        self.compiling: tuple[int, Future] | None = None
        self.failed: set[int] = set()
        self.overruns = 0
        self._worker: ThreadPoolExecutor | None = None      # where model steps run, timed
        self.running: Future | None = None      # a step past its deadline, still running

    def inline(self) -> bool:
        """Whether a program this stream lacks is compiled at its step, the loop waiting:
        without a deadline, and for its first program (before the loop runs)."""
        return self.deadline_s is None or not self.compiled

    def busy(self) -> bool:
        """Whether a step past its deadline still runs (its outputs, once done, unused)."""
        if self.running is not None and self.running.done():
            self.running = None              # its outputs came too late to be anyone's
        return self.running is not None

    def run(self, args: tuple) -> tuple:
        """The jitted step on `args` (its capacity's program compiled here if this stream has
        not yet): the state (on the device) and the outputs as numpy."""
        self.compile_inline(args)
        return _call(self._step, args)

    def run_in_time(self, args: tuple) -> tuple | None:
        """`run`, timed: with a deadline, in this stream's worker thread, None where it is not
        done by then (it runs on, `running`, its outputs never used). A step slower than the
        model's period is an overrun: counted (`overruns`) and logged."""
        self.compile_inline(args)
        started = perf_counter()
        if self.deadline_s is None:
            outcome = _call(self._step, args)
        else:
            if self._worker is None:
                self._worker = ThreadPoolExecutor(1, thread_name_prefix="gst_jax.stream.step")
                weakref.finalize(self, self._worker.shutdown, wait=False)
            job = self._worker.submit(_call, self._step, args)
            try:
                outcome = job.result(timeout=self.deadline_s)
            except TimeoutError:             # logged as constant velocity's start
                self.running, outcome = job, None
        seconds = perf_counter() - started
        if seconds > self.step_s:
            self.overruns += 1
            if outcome is not None:          # waited for: deadline_s None, or beyond step_s
                log = logger.warning if self.overruns == 1 else logger.debug
                log("frame %d: the model's step over %d slots took %.3f s, longer than its "
                    "period (%g s; overrun %d)", args[4], args[1].capacity, seconds,
                    self.step_s, self.overruns)
        return outcome

    def compile_inline(self, args: tuple) -> None:
        """Compile the step for `args`, the loop waiting, unless this stream has it."""
        capacity = args[1].capacity
        if capacity not in self.compiled:
            self.compiled[capacity] = _compile(self._step, args, self._config, self.step_s, "")

    def compile_behind(self, args: tuple) -> None:
        """Compile the step for `args` in the background (`collect` takes it)."""
        self.compiling = (args[1].capacity, _compiler().submit(
            _compile, self._step, args, self._config, self.step_s, " in the background"))

    def collect(self) -> str | None:
        """Take the background compile that has finished: its program is this stream's; a
        refusal (memory) is raised here; another failure returned in words, that capacity
        not tried again."""
        if self.compiling is None or not self.compiling[1].done():
            return None
        capacity, job = self.compiling
        self.compiling = None
        try:
            self.compiled[capacity] = job.result()
        except DataError:
            raise
        except Exception as error:           # constant velocity while it is needed
            self.failed.add(capacity)
            return (f"compiling the step over {capacity} slots failed: "
                    f"{type(error).__name__}: {str(error).splitlines()[0][:300]}")
        return None


def _compile(step: Any, args: tuple, config, step_s: float, where: str) -> float:
    """Compile the jitted `step` for `args` (its capacity's program, which jit's cache then
    holds), checked (`compile_checked`: the memory of every predictor's step; a large crowd
    where `config` is a gst_jax model's; issues 78, 94); logged, and returns its seconds."""
    capacity = args[1].capacity
    what = f"a stream step over {capacity} slots"
    started = perf_counter()
    compile_checked(step, args, config, capacity, what, slower_than_s=step_s)
    seconds = perf_counter() - started
    logger.info("compiled %s in %.1f s%s", what, seconds, where)
    return seconds


@functools.cache
def _compiler() -> ThreadPoolExecutor:
    """The thread that compiles streams' programs in the background, one at a time (each
    takes the cores it finds)."""
    return ThreadPoolExecutor(1, thread_name_prefix="gst_jax.stream.compile")


def _call(step: Callable, args: tuple) -> tuple:
    """The jitted step on `args`: the state (on the device) and the outputs as numpy."""
    state, *outputs = step(*args)
    return (state, *jax.tree.map(np.asarray, outputs))
