"""Exact binomial intervals: how sure a measured coverage is, from its count alone.

**Clopper-Pearson** (`clopper_pearson`; Clopper & Pearson 1934): of n independent trials
with the same success probability p, k succeeded. The two-sided interval at confidence
1 - beta is [L, U] with

    L = 0 for k = 0, else the p where P(X >= k) = beta / 2, i.e. I_L(k, n - k + 1) = beta / 2,
    U = 1 for k = n, else the p where P(X <= k) = beta / 2, i.e. I_U(k + 1, n - k) = 1 - beta / 2,

X ~ Binomial(n, p) and I_x(a, b) the regularised incomplete beta function (P(X >= k) =
I_p(k, n - k + 1)). Guarantee: P(L <= p <= U) >= 1 - beta for every p and n (conservative:
each tail holds at most beta / 2), so an interval over whole paths that lies above
1 - alpha says the regions cover at their level, and one that lies below says they do not.

I_x(a, b) is evaluated in float64 by its continued fraction (Lentz's method, as in Numerical
Recipes' `betacf`), on the side x < (a + 1)/(a + b + 2) where it converges fast, by the
symmetry I_x(a, b) = 1 - I_{1-x}(b, a) on the other; L and U by bisection on x, I being
increasing in x, down to adjacent floats. The standard library only: no numpy, no scipy
(tests/test_whole_path.py holds it to scipy.stats.binomtest(k, n).proportion_ci(
method="exact") within 1e-9).
"""

from __future__ import annotations

import math

_TINY = 1e-300
_EPSILON = 1e-15


def _continued_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of I_x(a, b) (modified Lentz), converging for x < (a+1)/(a+b+2)."""
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1)
    d = 1.0 / (d if abs(d) > _TINY else _TINY)
    value = d
    for m in range(1, 100_000):
        for numerator in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                          -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + numerator * d
            d = 1.0 / (d if abs(d) > _TINY else _TINY)
            c = 1.0 + numerator / c
            c = c if abs(c) > _TINY else _TINY
            value *= c * d
        if abs(c * d - 1.0) < _EPSILON:
            return value
    raise ArithmeticError(f"the incomplete beta's continued fraction did not converge for "
                          f"a={a}, b={b}, x={x}")


def regularized_beta(a: float, b: float, x: float) -> float:
    """I_x(a, b) = B(x; a, b) / B(a, b) for a, b > 0 and x in [0, 1], in float64."""
    if not (a > 0 and b > 0):
        raise ValueError(f"a and b must be positive, got a={a}, b={b}")
    if x <= 0:
        return 0.0
    if x >= 1:
        return 1.0
    log_front = (a * math.log(x) + b * math.log1p(-x)
                 - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)))
    if x < (a + 1) / (a + b + 2):
        return math.exp(log_front) * _continued_fraction(a, b, x) / a
    return 1.0 - math.exp(log_front) * _continued_fraction(b, a, 1.0 - x) / b


def _solve(a: float, b: float, target: float) -> float:
    """The x in [0, 1] with I_x(a, b) = target, by bisection down to adjacent floats."""
    low, high = 0.0, 1.0
    while True:
        middle = 0.5 * (low + high)
        if middle <= low or middle >= high:
            return middle
        if regularized_beta(a, b, middle) < target:
            low = middle
        else:
            high = middle


def clopper_pearson(k: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """The exact two-sided `confidence` interval (lower, upper) for a binomial proportion, k
    successes of n trials (this module's docstring); (0, 1) for n = 0."""
    k, n = int(k), int(n)
    if not 0 <= k <= n:
        raise ValueError(f"need 0 <= k <= n, got k={k}, n={n}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie strictly between 0 and 1, got {confidence}")
    tail = (1 - confidence) / 2
    lower = 0.0 if k == 0 else _solve(k, n - k + 1, tail)
    upper = 1.0 if k == n else _solve(k + 1, n - k, 1 - tail)
    return lower, upper
