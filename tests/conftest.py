"""Test-session settings: one persistent XLA compilation cache for this process and the
commands the tests start, so that a program several tests build compiles once; programs
compiled at LLVM's lowest optimisation level, since the suite's time goes to compiling them,
not to running them; the longest test files first; and the compiled programs let go after a
test file once a worker holds many memory maps, since every program holds some and Linux's
limit is 65530 (docs/commands.md), where XLA aborts; and each test file's name as its first
test starts (file_progress.py), where the quiet run writes only dots."""

from __future__ import annotations

import gc
import os
import tempfile

# Before JAX starts its CPU backend; the commands the tests start inherit it. A cold compile
# of a training step took 57 s at the default level and 27 s at level 0 (2-core CPU), the
# loss the same; XLA:CPU's older (non-MLIR) fusion emitters compile a training step's
# programs in 8-11 s of backend time against 14-17 s (tests/conftest.py's flags, 2-core AMD
# EPYC, jaxlib 0.10.2), the results equal within the suite's tolerances. One LLVM module per
# program, not one split for parallel code generation: with a worker per core there is no core
# to spare, and the first call of a one-layer training step took 5.9 s of CPU against 6.5 s
# (its steps 0.85 s against 1.0 s, with the same loss; quiet 2-core EPYC, one core).
SUITE_XLA_FLAGS = ["--xla_backend_optimization_level=0", "--xla_cpu_use_fusion_emitters=false",
                   "--xla_cpu_parallel_codegen_split_count=1"]
USER_XLA_FLAGS = os.environ.get("XLA_FLAGS", "")
os.environ["XLA_FLAGS"] = " ".join([USER_XLA_FLAGS, *SUITE_XLA_FLAGS]).strip()

import jax  # noqa: E402
import pytest  # noqa: E402
from file_progress import FileProgress  # noqa: E402

from gst_jax import compiles, stream  # noqa: E402
from gst_jax.private_folders import private_folder  # noqa: E402
from gst_jax.training import step  # noqa: E402

# Streams wait for the model (`Stream(deadline_s=None)`) unless a test gives a deadline: on a
# loaded 2-core VM a 3 ms step once took over a model period and fell back to constant velocity
# (tests/test_stream_capacity.py gives deadlines, held to by its stand-ins, not by the clock).
stream.DEADLINE_S = None

# The suite's cache is this user's alone, its entries checked, as the commands require.
CACHE = str(private_folder(os.path.join(tempfile.gettempdir(),
                                        f"gst_jax_tests_xla_cache_{os.getuid()}")))
compiles.check_cache_entries()
os.environ["JAX_COMPILATION_CACHE_DIR"] = CACHE
os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)

# Worker processes stay far below Linux's limit of 65530 memory maps: no test file added more
# than 5,400 of them, and a worker held 10,300 at most after its files (2-core EPYC, 599 tests).
MAPS_KEPT = 30_000
# The longest files start first (pyproject.toml keeps xdist to this order), so that no worker
# is left with one of them while the other has finished: their slowest tests' seconds, summed,
# on the 2-core VM beside a training (2026-12-07): 239, 167, 167, 145, 115, 112, 104, 98, 75,
# 65, 54, 50.
LONGEST_FIRST = ("test_train.py", "test_stops_and_faults.py", "test_docs.py",
                 "test_parallel.py", "test_own_data.py", "test_trajnet_submission.py",
                 "test_sweep.py", "test_numerics.py", "test_install.py", "test_navigation.py",
                 "test_pretrained.py", "test_parity.py")


def pytest_collection_modifyitems(items):
    def rank(item):
        name = item.path.name
        return LONGEST_FIRST.index(name) if name in LONGEST_FIRST else len(LONGEST_FIRST)
    items.sort(key=rank)                     # stable: each file's tests keep their order


# Each test file's name as its first test starts (file_progress.py), where the terminal shows
# none: in the process that writes to it, under -q or several workers.
_file_progress: FileProgress | None = None


@pytest.hookimpl(trylast=True)              # after the terminal reporter is registered
def pytest_configure(config):
    global _file_progress
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    verbosity, workers = config.getoption("verbose"), config.getoption("numprocesses", None)
    if hasattr(config, "workerinput") or reporter is None or verbosity > 0 or (
            verbosity == 0 and not workers):             # pytest writes the names itself
        return

    def write_line(text: str) -> None:
        if reporter._tw.width_of_current_line:           # after a line of dots
            reporter._tw.line()
        reporter._tw.line(text)
    _file_progress = FileProgress(write_line)


def pytest_runtest_logreport(report):
    if _file_progress is not None:
        gateway = getattr(getattr(report, "node", None), "gateway", None)   # xdist's worker
        _file_progress.report(report.nodeid, report.when, getattr(gateway, "id", None))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After a test file, let its compiled programs go once the worker holds more than
    MAPS_KEPT memory maps; below that the next file reuses them (and their traces)."""
    yield
    maps = compiles.memory_maps()
    if maps is None or maps[0] > MAPS_KEPT:
        step._last_train_step.cache_clear()
        jax.clear_caches()
        gc.collect()


@pytest.fixture
def own_compilation_cache():
    """The test sets a compilation cache of its own; the session's is set back after it."""
    folder = jax.config.jax_compilation_cache_dir
    threshold = jax.config.jax_persistent_cache_min_compile_time_secs
    yield
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", threshold)
    compiles.jax_cache.reset_cache()
