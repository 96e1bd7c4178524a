"""The conformal update alone: GenSafeNav's per-track DtACI loop beside one jitted call.

    python benchmarks/bench_conformal.py                      # 50 people x 5 steps, 200 steps
    python benchmarks/bench_conformal.py --humans 20 --steps 400

GenSafeNav's ROS 2 node keeps one DtACI object per person and horizon step (250 for 50
people and 5 steps) and, every time step, for each person (a Python loop) and each k = 1..5
(a loop), feeds that object its horizon-k score (present from step k on: feedback is k steps
late) with `update_true_value` and reads its radius with `make_prediction`, clipped to
[0, 1] m. `GenSafeNavDtACI` below re-implements that structure faithfully (per-object numpy
arrays, np.vectorize'd pinball loss, np.exp, np.random.choice from numpy's global RNG, list
appends for its logs), with GenSafeNav's loss in both (its np.vectorize given `otypes` so
that its integer-truncation bug is not timed as a different computation).

Ours is `gst_jax.conformal.dtaci(loss="gensafenav", r_max=1.0)`, one jitted call vmapped
over 50 x 5 instances per time step (numpy in, numpy out, `block_until_ready`), fed the
uniforms numpy's global RNG gave the loop (`np.random.choice(K, p=p)` draws one
`random_sample()`), so both must give the same radii: checked in float64 (to 1e-12) and
reported in float32 (the timed dtype). Times are medians over the time steps after one
warm-up pass. Further rows: the pooled modes (one instance per horizon step, the batch of 50
scores taken sequentially or as one mean step) and ACI with a window of 1000, per track and
pooled, to show what those cost.
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from common import print_table, record
from gst_jax import conformal

GAMMAS = np.array([0.05, 0.1, 0.2])
ALPHA = 0.1


class GenSafeNavDtACI:
    """GenSafeNav's DtACI (dt_aci/one_step_dtai.py) in its structure: one object, numpy
    arrays of K experts, the global RNG, logs as lists."""

    _zero_min = staticmethod(np.vectorize(lambda x: min(x, 0), otypes=[float]))

    def __init__(self, alpha=ALPHA, gammas=GAMMAS, sigma=1 / 1000, eta=2.72,
                 initial_pred=0.5):
        self.alpha, self.gammas, self.sigma, self.eta = alpha, gammas, sigma, eta
        self.true_values, self.predictions, self.errors, self.coverage = [], [], [], []
        self.gamma_sequence, self.weighted_average_prediction_sequence = [], []
        self.num_experts = len(gammas)
        self.initial_pred = initial_pred
        self.expert_predictions = np.full(self.num_experts, initial_pred)
        self.expert_weights = np.ones(self.num_experts)
        self.current_expert = np.random.choice(np.arange(self.num_experts))
        self.expert_probs = np.full(self.num_experts, 1 / self.num_experts)
        self.last_prediction = initial_pred

    def pinball(self, u):
        return self.alpha * u - self._zero_min(u)

    def make_prediction(self):
        if len(self.true_values) == 0:
            self.last_prediction = self.initial_pred
            return self.initial_pred
        prediction = self.expert_predictions[self.current_expert]
        self.last_prediction = prediction
        return prediction

    def update_true_value(self, truth):
        self.true_values.append(truth)
        prediction = self.last_prediction
        self.predictions.append(prediction)
        self.gamma_sequence.append(self.gammas[self.current_expert])
        self.weighted_average_prediction_sequence.append(
            np.sum(self.expert_probs * self.expert_predictions))
        expert_losses = self.pinball(truth - self.expert_predictions)
        self.expert_predictions -= self.gammas * (
            self.alpha - (self.expert_predictions < truth).astype(float))
        bar_weights = self.expert_weights * np.exp(-self.eta * expert_losses)
        next_weights = (1 - self.sigma) * bar_weights / np.sum(bar_weights) \
            + self.sigma / self.num_experts
        self.expert_probs = next_weights / np.sum(next_weights)
        self.current_expert = np.random.choice(np.arange(self.num_experts), p=self.expert_probs)
        self.expert_weights = next_weights
        self.errors.append(prediction - truth)
        self.coverage.append(float(prediction >= truth))


def stream(steps: int, humans: int, horizon: int, seed: int):
    """Scores (T, N, P), Rayleigh with scale 0.15 k m at horizon k, present from step k on."""
    rng = np.random.default_rng(seed)
    k = np.arange(1, horizon + 1)
    scores = rng.rayleigh(1.0, (steps, humans, horizon)) * 0.15 * k
    present = np.arange(steps)[:, None, None] >= k[None, None, :]
    return scores, np.broadcast_to(present, scores.shape).copy()


def gensafenav_loop(scores, present, seed: int):
    """-> radii (T, N, P) and seconds per time step. The objects are built first (their
    constructors draw from the global RNG), then the RNG is seeded."""
    steps, humans, horizon = scores.shape
    objects = [[GenSafeNavDtACI(initial_pred=0.1 * (k + 1)) for k in range(horizon)]
               for _ in range(humans)]
    np.random.seed(seed)
    radii, seconds = np.zeros(scores.shape), []
    for t in range(steps):
        start = time.perf_counter()
        for n in range(humans):
            for k in range(horizon):
                if present[t, n, k]:
                    objects[n][k].update_true_value(scores[t, n, k])
                radii[t, n, k] = float(np.clip(objects[n][k].make_prediction(), 0.0, 1.0))
        seconds.append(time.perf_counter() - start)
    return radii, seconds


def uniforms_of(present, seed: int) -> np.ndarray:
    """The uniform each update of the loop drew, in the loop's order (0 where none)."""
    rng = np.random.RandomState(seed)
    uniforms = np.zeros(present.shape)
    for index in zip(*np.nonzero(present)):          # C order: t, then n, then k
        uniforms[index] = rng.random_sample()
    return uniforms


def per_track_radii(method, q0, scores, present, uniforms, dtype):
    """Ours, one jitted call per time step -> radii (T, N, P) and seconds per step."""
    update = jax.jit(jax.vmap(jax.vmap(method.update)))
    state = jax.vmap(jax.vmap(lambda q: method.init(q, dtype=dtype)))(jnp.asarray(q0, dtype))
    radii, seconds = np.zeros(scores.shape), []
    for t in range(scores.shape[0]):
        args = (scores[t, ..., None].astype(dtype), present[t, ..., None])
        uniform = uniforms[t].astype(dtype)
        start = time.perf_counter()
        state, radius = update(state, *args, uniform=uniform)
        radii[t] = np.asarray(jax.block_until_ready(radius))
        seconds.append(time.perf_counter() - start)
    return radii, seconds


def median_ms_per_step(update, state, inputs) -> float:
    """Median over the steps of one jitted call from numpy inputs to numpy radii, after a
    warm-up pass over every step."""
    for _ in range(2):                       # a warm-up pass, then the timed one
        seconds = []
        for args in inputs:
            start = time.perf_counter()
            state, radius = update(state, *args)
            np.asarray(jax.block_until_ready(radius))
            seconds.append(time.perf_counter() - start)
    return 1e3 * statistics.median(seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--humans", type=int, default=50)
    parser.add_argument("--horizon", type=int, default=5)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--note", default="", help="the machine's load, for the record")
    args = parser.parse_args()
    n, p = args.humans, args.horizon
    scores, present = stream(args.steps, n, p, args.seed)
    q0 = 0.1 * np.arange(1, p + 1) * np.ones((n, 1))
    method = conformal.dtaci(ALPHA, tuple(GAMMAS), loss="gensafenav", r_max=1.0)

    gensafenav_loop(scores, present, args.seed)                      # warm-up pass
    theirs, loop_seconds = gensafenav_loop(scores, present, args.seed)
    uniforms = uniforms_of(present, args.seed)
    with jax.enable_x64(True):
        exact, _ = per_track_radii(method, q0, scores, present, uniforms, jnp.float64)
    per_track_radii(method, q0, scores, present, uniforms, jnp.float32)   # compile, warm up
    ours, our_seconds = per_track_radii(method, q0, scores, present, uniforms, jnp.float32)
    float64_gap = float(np.max(np.abs(exact - theirs)))
    float32_gap = np.abs(ours - theirs)
    assert float64_gap <= 1e-12, f"float64 radii differ from the loop's by {float64_gap}"

    loop_ms = 1e3 * statistics.median(loop_seconds)
    ours_ms = 1e3 * statistics.median(our_seconds)
    rows = [record("conformal", workload=f"per-track DtACI, {n} x {p}", method="GenSafeNav loop",
                   ms_per_step=loop_ms, note=args.note),
            record("conformal", workload=f"per-track DtACI, {n} x {p}", method="ours (jit+vmap)",
                   ms_per_step=ours_ms, speedup=loop_ms / ours_ms,
                   float64_max_gap=float64_gap, float32_max_gap=float(float32_gap.max()),
                   float32_share_off=float(np.mean(float32_gap > 1e-4)), note=args.note)]

    steps = range(args.steps)
    pooled = [(scores[t].T.astype(np.float32), present[t].T, np.float32(0.5)) for t in steps]
    for batch in conformal.BATCH_MODES:
        pooled_method = conformal.dtaci(ALPHA, tuple(GAMMAS), batch=batch)
        update = jax.jit(jax.vmap(lambda state, scores, mask, uniform, m=pooled_method:
                                  m.update(state, scores, mask, uniform=uniform),
                                  (0, 0, 0, None)))
        state = jax.vmap(pooled_method.init)(np.float32(0.1) * np.arange(1, p + 1))
        ms = median_ms_per_step(update, state, pooled)
        rows.append(record("conformal", workload=f"pooled DtACI, {p} x batch {n}",
                           method=f"ours, batch={batch}", ms_per_step=ms, note=args.note))
    aci = conformal.aci(ALPHA, 0.005, 1000)
    aci_state = jax.vmap(lambda _: aci.init())(np.arange(p))
    ms = median_ms_per_step(jax.jit(jax.vmap(aci.update)), aci_state,
                            [a[:2] for a in pooled])
    rows.append(record("conformal", workload=f"pooled ACI W=1000, {p} x batch {n}",
                       method="ours", ms_per_step=ms, note=args.note))
    per_track = [(scores[t, ..., None].astype(np.float32), present[t, ..., None]) for t in steps]
    aci_state = jax.vmap(jax.vmap(lambda _: aci.init()))(np.zeros((n, p)))
    ms = median_ms_per_step(jax.jit(jax.vmap(jax.vmap(aci.update))), aci_state, per_track)
    rows.append(record("conformal", workload=f"per-track ACI W=1000, {n} x {p}",
                       method="ours", ms_per_step=ms, note=args.note))

    print(f"{jax.devices()[0].platform}; radii of ours vs the loop: float64 max gap "
          f"{float64_gap:.1e}, float32 max gap {float32_gap.max():.1e} "
          f"({np.mean(float32_gap > 1e-4):.2%} of radii off by > 1e-4)")
    print_table(rows, ["workload", "method", "ms_per_step", "speedup"])


if __name__ == "__main__":
    main()
