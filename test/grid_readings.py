"""Test helper: the interpolated radio map's grid values as one dense array."""
from __future__ import annotations

import numpy as np

from indoor_loc.wifi.types import ApReadings


def assert_grid_equals(readings: ApReadings, sums: np.ndarray, expect: np.ndarray) -> None:
    """The grid's readings (gathered AP column by AP column) and its per-point sums equal ``expect``
    (grid points × APs) to 1e-12."""
    got = np.zeros_like(expect)
    for col in range(expect.shape[1]):
        r, v, _ = readings.gather(np.array([col]))
        got[r, col] = v
    np.testing.assert_allclose(got, expect, atol=1e-12)
    np.testing.assert_allclose(sums, expect.sum(axis=1), atol=1e-12)
