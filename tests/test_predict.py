"""The prediction API: make_batch from NaN-marked observations, jitted predict, compiles."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import warnings
from pathlib import Path
from unittest import mock

import jax
import numpy as np
import pytest

import gst_jax
from gst_jax import compiles, predict as predict_module, resources
from gst_jax.compiles import count_compiles
from gst_jax.errors import DataError
from gst_jax.model import Controls
from gst_jax.predict import Chunking, checks
from gst_jax.rollout import rollout

CONFIG = gst_jax.ModelConfig()
K = 3


def observations(num_pedestrians: int, seed: int = 0) -> np.ndarray:
    """(1, 8, N, 2) walkers; the last one appears at step 6, the first is lost at step 7."""
    rng = np.random.default_rng(seed)
    xy = np.cumsum(rng.normal(0.4, 0.05, (1, 8, num_pedestrians, 2)), axis=1)
    xy += rng.uniform(-4, 4, (1, 1, num_pedestrians, 2))
    xy[0, :6, -1] = np.nan
    xy[0, 7, 0] = np.nan
    return xy


def test_predict_from_nan_marked_observations():
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K)
    xy = observations(5)
    prediction = predict(params, jax.random.key(1), gst_jax.make_batch(xy))
    assert prediction.positions.shape == (K, 1, 12, 8, 2)
    assert prediction.sampled_adjacency.shape == (K, 1, 19, 8, 9)
    assert prediction.edge_probs.shape == (K, 1, 19, 8, 1, 9)
    np.testing.assert_array_equal(prediction.predicted_mask[0], [0, 1, 1, 1, 1, 0, 0, 0])
    positions = np.asarray(prediction.positions)
    assert np.all(np.isfinite(positions[:, 0, :, 1:5]))
    # Not predicted (pedestrian 0 was lost at the last step; 5-7 are padding): NaN, which no
    # planner can mistake for a position.
    assert np.all(np.isnan(positions[:, 0, :, [0, 5, 6, 7]]))
    # Positions continue from the last observation by the predicted displacements.
    np.testing.assert_allclose(positions[:, 0, 0, 1:5],
                               xy[0, 7, 1:5] + prediction.displacements[:, 0, 0, 1:5], atol=1e-5)
    # n = 1: every predicted target picks exactly one neighbour (possibly the ghost).
    np.testing.assert_allclose(np.asarray(prediction.sampled_adjacency)[:, 0, 8:, 1:5].sum(-1), 1.0)
    # K samples are different draws of the graph.
    assert not np.array_equal(prediction.sampled_adjacency[0], prediction.sampled_adjacency[1])
    # Inside a planner's own jit: the same single vmap over samples, the same futures.
    batch = gst_jax.make_batch(xy)
    inside = jax.jit(lambda p, k: predict(p, k, batch).positions)(params, jax.random.key(1))
    np.testing.assert_allclose(inside, prediction.positions, rtol=0, atol=1e-5)


def test_samples_share_the_observation_pass_without_changing_them():
    """predict computes the observed edge probabilities once; each sample equals a rollout
    that computes them itself."""
    config = gst_jax.ModelConfig(output="gaussian")
    params = gst_jax.init_params(config, jax.random.key(0))
    batch = gst_jax.make_batch(observations(6))
    key = jax.random.key(3)
    prediction = gst_jax.make_predict(config, num_samples=K)(params, key, batch)
    controls = Controls.from_config(config)
    alone_rollout = jax.jit(lambda sample_key: rollout(params, sample_key, batch, config,
                                                       controls, hard=True, deterministic=True))
    for k, sample_key in enumerate(jax.random.split(key, K)):
        alone = alone_rollout(sample_key)
        np.testing.assert_allclose(prediction.displacements[k], alone.displacements, atol=1e-5)
        np.testing.assert_allclose(prediction.edge_probs[k], alone.edge_probs, atol=1e-6)


def test_predict_compiles_once_per_bucket():
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False)
    keys = [jax.random.key(seed) for seed in range(5)]

    def run(num_pedestrians: int, seed: int):
        out = predict(params, keys[seed], gst_jax.make_batch(observations(num_pedestrians, seed)))
        return jax.block_until_ready(out)

    with count_compiles() as first_two_buckets:
        assert run(3, 0).positions.shape[3] == 8
        assert run(9, 1).positions.shape[3] == 16
    assert first_two_buckets.count >= 2
    with count_compiles() as same_buckets:                     # buckets 8 and 16 again
        for num_pedestrians, seed in [(5, 2), (8, 3), (12, 4), (3, 0), (16, 1)]:
            run(num_pedestrians, seed)
    assert same_buckets.count == 0
    with count_compiles() as new_bucket:                       # the counter sees a new shape
        assert run(20, 2).positions.shape[3] == 24
    assert new_bucket.count >= 1


def test_compiling_near_the_kernel_s_limit_on_memory_maps_warns_once(monkeypatch):
    held = iter([40_000, 50_000, 60_000])               # maps after each compile; limit 65530
    monkeypatch.setattr(compiles, "memory_maps", lambda: (next(held), 65530))
    triple = jax.jit(lambda x: 3 * x)
    with count_compiles() as counter:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            triple(np.ones(2))                          # 61 % of the limit: quiet
        with pytest.warns(UserWarning, match=r"holds 50000 memory maps of the 65530 .* "
                                             r"sudo sysctl -w vm.max_map_count=262144"):
            triple(np.ones(3))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            triple(np.ones(4))                          # said once
    assert counter.count == 3


def test_memory_maps_are_read_from_the_kernel_on_linux():
    maps = compiles.memory_maps()
    if maps is None:
        pytest.skip("not Linux")
    held, limit = maps
    assert 0 < held < limit


# --- memory: chunked samples, the estimate, the refusal ---------------------------------------

def test_samples_in_chunks_are_the_samples_of_one_vmap():
    """A budget below any program's need computes one sample at a time and the observed
    steps one by one: the same keys, so the same draws (graphs equal) and the same numbers up
    to float32 rounding."""
    config = gst_jax.ModelConfig(output="gaussian")               # samples its Gaussian too
    params = gst_jax.init_params(config, jax.random.key(0))
    batch = gst_jax.make_batch(np.concatenate([observations(13, 0), observations(13, 1)]))
    key = jax.random.key(3)
    one_at_a_time = gst_jax.make_predict(config, num_samples=K, memory_budget_bytes=1)
    chunked = one_at_a_time(params, key, batch)
    assert one_at_a_time.chunking(params, key, batch) == Chunking(1, 1, *[mock.ANY] * 3)
    # Choosing compiled the single vmap first, to measure it: jit's cache holds it.
    whole = one_at_a_time._program(K, None)(params, key, batch, None)

    np.testing.assert_array_equal(chunked.sampled_adjacency, whole.sampled_adjacency)
    np.testing.assert_array_equal(chunked.predicted_mask, whole.predicted_mask)
    # The edge selector's observed steps, one at a time, compute what all at once do, bit for
    # bit; a vmap over 1 sample instead of K may order the rollout's sums otherwise: each of
    # its obs_len + pred_len sequential steps may add an ulp of what it carries, and positions
    # sum the displacements.
    steps = config.obs_len + config.pred_len
    ulp = np.finfo(np.float32).eps
    np.testing.assert_array_equal(np.isnan(chunked.positions), np.isnan(whole.positions))
    for name in ("displacements", "mu", "sigma", "corr", "positions"):
        reference = np.asarray(getattr(whole, name))
        largest = np.nanmax(np.abs(reference))
        np.testing.assert_allclose(getattr(chunked, name), reference, rtol=0,
                                   atol=steps * ulp * largest, err_msg=name)
    np.testing.assert_allclose(chunked.edge_probs, whole.edge_probs, rtol=0, atol=steps * ulp)


def test_a_prediction_that_cannot_fit_is_refused_in_one_line_before_it_runs(monkeypatch):
    monkeypatch.setattr(checks, "COMPILER_BYTES", 0)     # the compiler fits (below)
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (2 ** 16, "under this process's cgroup memory limit"))
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False)
    with count_compiles() as compiles:
        with pytest.raises(DataError, match=(
                r"^predicting 3 samples of a scene of 5 people needs \d+ [KM]iB at least \(one "
                r"sample at a time\); 64 KiB is available \(under this process's cgroup memory "
                r"limit\); use fewer people per scene or more memory$")):
            predict(params, jax.random.key(1), gst_jax.make_batch(observations(5)))
    assert compiles.count == 2             # measured: the single vmap, then one at a time


def test_a_chunked_shape_compiles_once_and_a_small_one_keeps_its_single_program():
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    batch = gst_jax.make_batch(observations(5))
    frugal = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False, memory_budget_bytes=1)
    with count_compiles() as choosing:
        jax.block_until_ready(frugal(params, jax.random.key(1), batch))
    assert choosing.count == 2             # the single vmap (measured), one at a time (run)
    with count_compiles() as again:
        for seed in range(3):
            jax.block_until_ready(frugal(params, jax.random.key(seed), gst_jax.make_batch(
                observations(3 + seed, seed))))
    assert again.count == 0

    default = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False)
    with count_compiles() as small:
        jax.block_until_ready(default(params, jax.random.key(1), batch))
        jax.block_until_ready(default(params, jax.random.key(2), batch))
    assert small.count == 1                # measured and run: one program
    assert default.chunking(params, jax.random.key(1), batch).samples_at_once == K


def test_the_memory_left_under_cgroup_limits_is_read_for_v1_and_v2(tmp_path):
    def write(directory, **files):
        directory.mkdir(parents=True, exist_ok=True)
        for name, text in files.items():
            (directory / name.replace("_", ".", 1)).write_text(text)

    # v2: this process's cgroup has 3 GiB, 1 GiB used of which 0.25 GiB inactive file pages
    # (reclaimable); its parent's limit is looser, the root has none.
    write(tmp_path / "a" / "b", memory_max=str(3 * 2 ** 30), memory_current=str(2 ** 30),
          memory_stat=f"anon 1\ninactive_file {2 ** 28}\n")
    write(tmp_path / "a", memory_max=str(8 * 2 ** 30), memory_current=str(2 ** 30),
          memory_stat="")
    assert resources.cgroup_headroom("0::/a/b\n", tmp_path) == 2 * 2 ** 30 + 2 ** 28
    # No limit anywhere ("max"): None, and MemAvailable decides.
    write(tmp_path / "c", memory_max="max", memory_current="5")
    assert resources.cgroup_headroom("0::/c\n", tmp_path) is None
    # v1: the memory controller's own hierarchy; "no limit" is a huge number.
    write(tmp_path / "memory" / "job", memory_limit_in_bytes=str(2 ** 31),
          memory_usage_in_bytes=str(2 ** 30), memory_stat="total_inactive_file 0\n")
    write(tmp_path / "memory", memory_limit_in_bytes=str(2 ** 63 - 4096),
          memory_usage_in_bytes="7")
    assert resources.cgroup_headroom("4:memory:/job\n3:cpu:/job\n", tmp_path) == 2 ** 30


def test_the_memory_available_on_this_machine_is_known():
    available = resources.available_memory(jax.devices()[0])
    if available is None:
        pytest.skip("no memory figures on this platform")
    left, source = available
    assert 0 < left and source


def test_predict_s_names_stay_importable_from_gst_jax_predict_where_they_moved():
    """The chunking, the cost of a program, the checks before it runs and the OS's figures
    have modules of their own; every public name `gst_jax.predict` had is still its own,
    the very object of the module that defines it now."""
    from gst_jax.predict import chunking, cost

    homes = {chunking: ["Chunking", "DEFAULT_MEMORY_BUDGET", "CHUNKING_SLACK"],
             cost: ["Estimate", "estimate", "operation_count", "CPU_RUNTIME_MARGIN"],
             checks: ["check_compiler_room", "check_memory", "crowd_notice", "compile_checked",
                      "COMPILER_BYTES", "SUGGESTED_CANDIDATES", "CANDIDATES_PAY_ABOVE",
                      "LONG_CALL_S", "CPU_OPERATIONS_PER_CORE_SECOND"],
             resources: ["available_memory", "cgroup_headroom", "CGROUP_ROOT", "NO_LIMIT"],
             predict_module: ["Prediction", "Predictor", "make_predict"]}
    names = [name for moved in homes.values() for name in moved]
    assert sorted(predict_module.__all__) == sorted(names)
    for module, moved in homes.items():
        for name in moved:
            assert getattr(predict_module, name) is getattr(module, name), name


# --- large crowds: announced, and the compiler's own memory -----------------------------------

def test_a_crowd_above_the_crossover_with_the_exact_model_is_announced_in_one_line(monkeypatch):
    """Before a large crowd's first call: one warning with XLA's estimate of its memory and
    time that names the candidate neighbourhood; once per shape. The crossover is lowered to
    4 people and the time worth a word to none, so that a scene of 5 (8 slots) is "large"."""
    monkeypatch.setattr(checks, "CANDIDATES_PAY_ABOVE", 4)
    monkeypatch.setattr(checks, "LONG_CALL_S", 0.0)
    params = gst_jax.init_params(CONFIG, jax.random.key(0))
    predict = gst_jax.make_predict(CONFIG, num_samples=K, with_graph=False)
    batch = gst_jax.make_batch(observations(5))
    with pytest.warns(UserWarning) as said:
        jax.block_until_ready(predict(params, jax.random.key(1), batch))
    assert len(said) == 1
    assert said[0].filename == __file__                 # pointed at the caller's line
    assert re.fullmatch(
        r"predicting 3 samples of a scene of 5 people with the exact model needs about \S+ "
        r"(s|min) a call on \d+ idle CPU cores? and \d+ [KM]iB \(XLA's estimate\); above 4 people "
        r"the candidate neighbourhood is faster: candidates=16 \(--candidates 16; "
        r"docs/MODEL.md 2.4\)", str(said[0].message)), str(said[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        jax.block_until_ready(predict(params, jax.random.key(2), batch))     # said once


def test_the_crowd_notice_is_for_the_exact_model_above_the_crossover_on_a_cpu():
    cpu = jax.devices("cpu")[0]
    cost = predict_module.Estimate(xla_bytes=2 ** 30, bytes_needed=3 * 2 ** 29,
                    operations=40 * predict_module.CPU_OPERATIONS_PER_CORE_SECOND)
    above = predict_module.CANDIDATES_PAY_ABOVE + 1
    line = predict_module.crowd_notice(CONFIG, above, cost, cpu, "a stream step")
    cores = len(os.sched_getaffinity(0))
    assert line.startswith(f"a stream step with the exact model needs about {40 / cores:.2g} s "
                           f"a call on {cores} idle CPU core")
    assert "and 1.5 GiB (XLA's estimate); above " in line
    assert "candidates=16 (--candidates 16" in line
    assert predict_module.crowd_notice(CONFIG, above - 1, cost, cpu, "a step") is None
    assert predict_module.crowd_notice(CONFIG, above, cost, cpu, "a step",
                                       slower_than_s=41 / cores) is None
    with_candidates = gst_jax.ModelConfig(candidates=16)
    assert predict_module.crowd_notice(with_candidates, above, cost, cpu, "a step") is None


def test_the_operation_count_takes_a_loop_s_body_its_length_times():
    """XLA's cost analysis counts a loop's body once; the time estimate must not: a scan of
    5 matrix products (4 x 3 by 3 x 2: 48 operations each, 2 per multiply-add) and a sine of
    their result (8) counts 5 x 56."""
    y = np.ones((3, 2), np.float32)

    def body(carry, x):
        return carry, jax.numpy.sin(x @ y)

    def scanned(xs):
        return jax.lax.scan(body, 0.0, xs)[1]

    jaxpr = jax.make_jaxpr(scanned)(np.ones((5, 4, 3), np.float32)).jaxpr
    assert predict_module.operation_count(jaxpr) == 5 * (48 + 8)


def test_a_program_compiled_for_a_stream_is_checked_announced_and_not_compiled_again(
        monkeypatch):
    """`compile_checked`, what a stream calls before its step first runs at a capacity."""
    double = jax.jit(lambda x: 2 * x)
    x = np.ones((4, 3), np.float32)
    above = predict_module.CANDIDATES_PAY_ABOVE + 1
    with count_compiles() as compiled:
        with pytest.warns(UserWarning, match=r"^a stream step over 320 slots with the exact "
                                             r"model needs .* candidates=16"):
            cost = predict_module.compile_checked(double, (x,), CONFIG, above,
                                                  "a stream step over 320 slots",
                                                  slower_than_s=0.0)
        double(x).block_until_ready()
    assert compiled.count == 1                          # the call ran what was checked
    assert cost.operations == 12 and cost.bytes_needed > 0
    monkeypatch.setattr(resources, "available_memory",
                        lambda device: (2 ** 20, "under this process's cgroup memory limit "
                                                 "of 1.0 GiB"))
    with count_compiles() as compiled:
        with pytest.raises(DataError, match=(
                r"^a stream step: XLA's compiler needs about 256 MiB more than this process "
                r"holds, and 1 MiB is left \(under this process's cgroup memory limit of "
                r"1.0 GiB\); raise the limit$")):
            predict_module.compile_checked(jax.jit(lambda x: 3 * x), (x,), CONFIG, 8,
                                           "a stream step")
    assert compiled.count == 0                          # refused before compiling


# The child: load a model and a batch (nothing left to compile but the prediction), leave it
# 32 MiB of address space above what it holds, and predict as a command would (the library's
# `DataError` printed as `gst_jax.cli.run` prints it) or run `python -m gst_jax.predict`.
UNDER_A_LIMIT = """
import resource, sys
import jax, numpy as np, gst_jax
from gst_jax.errors import DataError
from gst_jax.predict.__main__ import main
config, params = gst_jax.load_pretrained("eth_d")
xy = np.cumsum(np.full((1, 8, 5, 2), 0.4), axis=1) + np.arange(5.0)[:, None]
batch, key = gst_jax.make_batch(xy), jax.block_until_ready(jax.random.key(1))
predict = gst_jax.make_predict(config, num_samples=3, with_graph=False)
held = next(int(line.split()[1]) for line in open("/proc/self/status")
            if line.startswith("VmSize:")) * 1024
resource.setrlimit(resource.RLIMIT_AS, (held + 32 * 2 ** 20, resource.RLIM_INFINITY))
if sys.argv[1] == "command":
    main(["pretrained:eth_d", "--out", "never-written.ndjson"])
try:
    predict(params, key, batch)
except DataError as error:
    raise SystemExit(f"error: {error}")
"""


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux's /proc")
@pytest.mark.parametrize("caller, work", [
    ("library", "predicting 3 samples of a scene of 5 people"),
    ("command", "python -m gst_jax.predict")])
def test_an_address_space_limit_too_small_for_the_compiler_is_refused_in_one_line(
        caller, work, tmp_path):
    """Under `ulimit -v` with less left than XLA's compiler takes, predict used to die inside
    it (std::bad_alloc, "LLVM ERROR: pthread_create failed", a segfault) without a word."""
    result = subprocess.run([sys.executable, "-c", UNDER_A_LIMIT, caller], capture_output=True,
                            text=True, timeout=600, cwd=tmp_path,
                            env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])})
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert re.fullmatch(
        rf"error: {re.escape(work)}: XLA's compiler needs about 256 MiB more than this process "
        r"holds, and \d+ MiB is left \(under this process's address-space limit of \d+\.\d "
        r"GiB, ulimit -v\); raise the limit", lines[-1]), result.stderr
    assert not (tmp_path / "never-written.ndjson").exists()
