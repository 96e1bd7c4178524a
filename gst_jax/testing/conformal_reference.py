"""Plain-numpy references of gst_jax.conformal's update equations: loops, float64, no jax.

Written from the papers' equations (split conformal; Gibbs & Candès 2021 for ACI;
Angelopoulos, Candès & Tibshirani 2023 for PID; Cleaveland, Lee, Pappas & Lindemann 2024
for the whole-path regions) and, for DtACI, from GenSafeNav's description of its port of
Gibbs & Candès 2022 (gst_jax/conformal/_src/dtaci.py), one score and one expert at a time,
for tests/test_conformal.py, tests/test_whole_path.py and benchmarks/bench_conformal.py to
compare the jitted versions with.

Each online method's function runs one instance over T time steps; at step t it gets a batch
of scores `scores[t]` (B,) of which `mask[t]` (B,) are present, and returns the radius in
force before each step and after the last: radii (T + 1,). `whole_path_region` and
`paths_inside` take calibration paths' scores (paths, P) at once.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np


def split_radius(scores, alpha: float) -> float:
    """The ceil((n+1)(1-alpha))-th smallest of the n scores; +inf when that exceeds n."""
    ordered = sorted(float(s) for s in scores)
    rank = math.ceil((len(ordered) + 1) * (1 - alpha))
    return math.inf if rank > len(ordered) else ordered[rank - 1]


def _empirical_quantile(window, level: float) -> float:
    """inf{r : (1/n) #{s <= r} >= level}: the ceil(level n)-th smallest score."""
    ordered = sorted(window)
    return ordered[math.ceil(level * len(ordered)) - 1]


def aci(scores, mask, alpha: float, gamma: float, window: int,
        radii_in_force=None, batch: str = "sequential") -> dict[str, np.ndarray]:
    """ACI (Gibbs & Candès 2021), pooled: err_t = fraction of the step's present scores above
    the radius in force (the current one, or `radii_in_force[t][b]`); alpha_{t+1} = alpha_t +
    gamma (alpha - err_t) ("mean"), or one such step per present score, each with its own
    miss ("sequential"); radius = the (1 - alpha_t) empirical quantile of the last `window`
    scores, +inf when alpha_t <= 0 or none were seen, 0 when alpha_t >= 1. A step without
    scores changes nothing. Returns radii (T+1,), levels (T+1,), errs (T,) (NaN: no score)."""
    level = float(alpha)
    recent: deque[float] = deque(maxlen=window)
    radius = math.inf
    radii, levels, errs = [radius], [level], []
    for t in range(len(scores)):
        present = [float(s) for s, m in zip(scores[t], mask[t]) if m]
        in_force = [radius if radii_in_force is None else float(radii_in_force[t][b])
                    for b, m in enumerate(mask[t]) if m]
        if not present:
            radii.append(radius)
            levels.append(level)
            errs.append(math.nan)
            continue
        misses = sum(1 for s, r in zip(present, in_force) if s > r)
        err = misses / len(present)
        if batch == "mean":
            level = level + gamma * (alpha - err)
        else:
            for s, r in zip(present, in_force):
                level = level + gamma * (alpha - (s > r))
        recent.extend(present)
        if level <= 0:
            radius = math.inf
        elif level >= 1:
            radius = 0.0
        else:
            radius = _empirical_quantile(recent, 1 - level)
        radii.append(radius)
        levels.append(level)
        errs.append(err)
    return {"radii": np.array(radii), "levels": np.array(levels), "errs": np.array(errs)}


def _pinball(u: float, alpha: float, loss: str) -> float:
    if loss == "consistent":             # pinball loss of the (1 - alpha) quantile
        return (1 - alpha) * u if u >= 0 else -alpha * u
    return alpha * u - min(u, 0.0)       # GenSafeNav's (the alpha quantile's), without its bug


def _draw(probs: list[float], uniform: float) -> int:
    """numpy's np.random.choice(K, p=probs) given its uniform: the first expert whose
    normalised cumulative probability exceeds it."""
    cumulative, total = [], 0.0
    for p in probs:
        total += p
        cumulative.append(total)
    return int(np.searchsorted(np.array(cumulative) / cumulative[-1], uniform, side="right"))


def dtaci(scores, mask, uniforms, alpha: float, gammas, eta: float, sigma: float, q0: float,
          loss: str = "consistent", output: str = "sample", r_max: float = math.inf,
          batch: str = "sequential") -> dict[str, np.ndarray]:
    """DtACI with experts holding radii (GenSafeNav). Per score s, for each expert i:
    u = s - q_i, l_i = pinball(u), q_i <- q_i - gamma_i (alpha - 1{q_i < s}),
    wbar_i = w_i exp(-eta l_i); then w_i <- (1 - sigma) wbar_i / sum(wbar) + sigma / K.
    batch="sequential": once per present score in order; "mean": once per step with the mean
    l_i and mean 1{q_i < s} over the present scores. Then p = w / sum(w), the expert drawn with
    uniforms[t] (steps with a score only), radius = clip(q_expert or sum p q, 0, r_max).
    Returns radii (T+1,), thresholds (T+1, K), probs (T+1, K), experts (T+1,)."""
    k = len(gammas)
    q = [float(q0)] * k
    w = [1.0] * k
    p = [1 / k] * k
    expert = 0

    def radius_now():
        value = q[expert] if output == "sample" else sum(pi * qi for pi, qi in zip(p, q))
        return min(max(value, 0.0), r_max)

    radii, thresholds, probs, experts = [radius_now()], [list(q)], [list(p)], [expert]
    for t in range(len(scores)):
        present = [float(s) for s, m in zip(scores[t], mask[t]) if m]
        if present:
            batches = [[s] for s in present] if batch == "sequential" else [present]
            for group in batches:
                losses = [sum(_pinball(s - q[i], alpha, loss) for s in group) / len(group)
                          for i in range(k)]
                misses = [sum(1.0 for s in group if q[i] < s) / len(group) for i in range(k)]
                q = [q[i] - gammas[i] * (alpha - misses[i]) for i in range(k)]
                bar = [w[i] * math.exp(-eta * losses[i]) for i in range(k)]
                w = [(1 - sigma) * bar[i] / sum(bar) + sigma / k for i in range(k)]
            p = [wi / sum(w) for wi in w]
            if output == "sample":
                expert = _draw(p, float(uniforms[t]))
        radii.append(radius_now())
        thresholds.append(list(q))
        probs.append(list(p))
        experts.append(expert)
    return {"radii": np.array(radii), "thresholds": np.array(thresholds),
            "probs": np.array(probs), "experts": np.array(experts)}


def pid(scores, mask, alpha: float, eta: float, k_i: float, c_sat: float, q0: float = 0.0,
        radii_in_force=None) -> dict[str, np.ndarray]:
    """Conformal PID control, P and I (Angelopoulos, Candès & Tibshirani 2023), pooled: per
    present score s in order, err = 1{s > radius in force} (the radius before the step, or
    `radii_in_force[t][b]`); p <- p + eta (err - alpha); S <- S + err - alpha; t <- t + 1;
    after the step, radius = max(p + K_I tan(S log(t) / (t C_sat)), 0), the tan +-inf outside
    (-pi/2, pi/2). Returns radii (T+1,), tracking (T+1,) p, misses (T+1,) S."""
    p, total, count = float(q0), 0.0, 0

    def radius_now():
        argument = total * math.log(max(count, 1)) / (max(count, 1) * c_sat)
        integrator = k_i * math.tan(argument) if abs(argument) < math.pi / 2 else \
            math.copysign(math.inf, argument)
        return max(p + integrator, 0.0)

    radius = radius_now()
    radii, tracking, misses = [radius], [p], [total]
    for t in range(len(scores)):
        for b, (s, m) in enumerate(zip(scores[t], mask[t])):
            if not m:
                continue
            in_force = radius if radii_in_force is None else float(radii_in_force[t][b])
            err = 1.0 if float(s) > in_force else 0.0
            p += eta * (err - alpha)
            total += err - alpha
            count += 1
        radius = radius_now()
        radii.append(radius)
        tracking.append(p)
        misses.append(total)
    return {"radii": np.array(radii), "tracking": np.array(tracking),
            "misses": np.array(misses)}


def whole_path_region(scores, mask, alpha: float, fit=None, scales=None,
                      scale_level: float | None = None) -> dict:
    """Normalised-max whole-path regions (Cleaveland et al. 2024), path by path: scales
    sigma_k = the ceil(level n_k)-th smallest (at least the first) of the n_k observed
    horizon-k scores of the `fit` paths (level 1 - alpha for None; +inf for none; at least
    the smallest positive float), unless given; each other path with an observed step gets
    m = max_k observed s_k / sigma_k; q = the split-conformal radius of those m; radii
    q sigma_k (+inf where either is). Returns scales (P,), scores (paths,) m (-inf for a path
    with no observed step), quantile, radii (P,), count."""
    scores = np.asarray(scores, np.float64)
    paths, horizon = scores.shape
    mask = np.ones((paths, horizon), bool) if mask is None else np.asarray(mask, bool)
    fit = np.zeros(paths, bool) if fit is None else np.asarray(fit, bool)
    if scales is None:
        level = 1 - alpha if scale_level is None else scale_level
        scales = []
        for k in range(horizon):
            seen = sorted(float(scores[i, k]) for i in range(paths) if fit[i] and mask[i, k])
            if not seen:
                scales.append(math.inf)
                continue
            rank = max(math.ceil(level * len(seen)), 1)
            scales.append(max(seen[rank - 1], np.finfo(np.float64).tiny))
    scales = [float(s) for s in scales]
    normalised, calibrating = [], []
    for i in range(paths):
        ratios = [float(scores[i, k]) / scales[k] for k in range(horizon) if mask[i, k]]
        normalised.append(max(ratios) if ratios else -math.inf)
        if ratios and not fit[i]:
            calibrating.append(normalised[-1])
    quantile = split_radius(calibrating, alpha)
    radii = [math.inf if math.isinf(s) or math.isinf(quantile) else quantile * s
             for s in scales]
    return {"scales": np.array(scales), "scores": np.array(normalised),
            "quantile": quantile, "radii": np.array(radii), "count": len(calibrating)}


def paths_inside(scores, mask, radii) -> np.ndarray:
    """Whether each path has every observed step's score within its step's radius."""
    return np.array([all(float(s) <= float(r) for s, m, r in zip(row, observed, radii) if m)
                     for row, observed in zip(scores, mask)])
