"""``indoor_loc.pf.filter.logsumexp_1d`` is SciPy's ``logsumexp`` bit for bit (the particle filter's
weights are normalised with it on every input; a different last bit would change the filter's path)."""
from __future__ import annotations

import numpy as np
from scipy.special import logsumexp

from indoor_loc.pf.filter import logsumexp_1d


def _same(x, y) -> bool:
    return bool(x == y or (np.isnan(x) and np.isnan(y)))


def test_logsumexp_1d_is_scipys_bit_for_bit():
    rng = np.random.default_rng(11)
    for k in range(3000):
        n = int(rng.integers(1, 1500))
        a = rng.normal(size=n) * rng.choice([0.01, 1.0, 30.0, 700.0])
        if k % 5 == 0:                              # ties at the maximum
            a[rng.integers(0, n, 3)] = a.max()
        if k % 7 == 0:
            a[rng.integers(0, n)] = -np.inf
        if k % 9 == 0:
            a = np.round(a)
        assert _same(logsumexp_1d(a), logsumexp(a))
    for a in ([-np.inf] * 4, [np.inf, 1.0], [np.nan, 1.0], [1e308, 1e308], [0.0], [-1e308, 5.0]):
        arr = np.asarray(a, float)
        assert _same(logsumexp_1d(arr), logsumexp(arr))
