"""Test-session settings: one persistent XLA compilation cache for this process and the
commands the tests start, so that a program several tests build compiles once."""

from __future__ import annotations

import os
import tempfile

import jax

CACHE = os.path.join(tempfile.gettempdir(), f"gst_jax_tests_xla_cache_{os.getuid()}")
os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
