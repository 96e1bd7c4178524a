"""Test-session settings: one persistent XLA compilation cache for this process and the
commands the tests start, so that a program several tests build compiles once; and the
compiled programs of each test file let go after it, since every program holds memory maps
and the whole suite in one process would otherwise approach Linux's limit of 65530 (README),
where XLA aborts."""

from __future__ import annotations

import gc
import os
import tempfile

import jax
import pytest

from gst_jax.training.step import make_train_step

CACHE = os.path.join(tempfile.gettempdir(), f"gst_jax_tests_xla_cache_{os.getuid()}")
os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    yield
    make_train_step.cache_clear()
    jax.clear_caches()
    gc.collect()
