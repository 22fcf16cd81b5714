"""The powed representation of RSS readings, the Sørensen distance between scans, reading ages and the
kernel-smoothing grid of a radio map (pure numpy/scipy; :mod:`indoor_loc.wifi.powed_knn` describes the method)."""
from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from indoor_loc.wifi.types import ApReadings

KERNEL_CUTOFF = 3.0                                   # the smoothing kernel is cut at this many bandwidths


def powed(rssi_dbm: ArrayLike, floor_dbm: float, beta: float) -> np.ndarray:
    """The powed representation of RSS values (dBm) -> [0, 1]; NaN -> 0."""
    r = np.nan_to_num(np.asarray(rssi_dbm, float), nan=-np.inf)
    return (np.clip(r - floor_dbm, 0.0, None) / -floor_dbm) ** beta


def smoothing_grid(pos: np.ndarray, z: np.ndarray, step_m: float, reach_m: float, bandwidth_m: float
                   ) -> tuple[np.ndarray, np.ndarray, Any, Any]:
    """Candidate grid of a map: per floor height, the points of a square grid of spacing ``step_m`` lying
    within ``reach_m`` of one of that floor's map scans. Returns (positions (C, 2), heights (C,),
    Gaussian kernel weights (C, M) sparse, exp(-d^2 / 2 h^2) for the same floor's map scans within 3 h,
    and a sparse (C, M) boolean of the map scans within ``reach_m``)."""
    from scipy import sparse
    from scipy.spatial import cKDTree
    grids, heights = [], []
    for zf in np.unique(z):
        p = pos[z == zf]
        lo = np.floor((p.min(axis=0) - reach_m) / step_m) * step_m
        hi = p.max(axis=0) + reach_m
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1e-9, step_m), np.arange(lo[1], hi[1] + 1e-9, step_m))
        g = np.column_stack([gx.ravel(), gy.ravel()])
        d, _ = cKDTree(p).query(g, distance_upper_bound=reach_m + 1e-9)
        grids.append(g[np.isfinite(d)])
        heights.append(np.full(int(np.isfinite(d).sum()), float(zf)))
    g = np.vstack(grids)
    gz = np.concatenate(heights)
    sep = 1e6                                       # floors never within a kernel of each other
    tree_g, tree_m = cKDTree(np.column_stack([g, gz * sep])), cKDTree(np.column_stack([pos, z * sep]))
    shape = (len(g), len(pos))

    def pairs(radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        coo = tree_g.sparse_distance_matrix(tree_m, radius, output_type="coo_matrix")
        return coo.row, coo.col, coo.data
    r, c, d = pairs(KERNEL_CUTOFF * bandwidth_m)
    w = sparse.csr_matrix((np.exp(-0.5 * (d / bandwidth_m) ** 2), (r, c)), shape=shape)
    r, c, _ = pairs(reach_m + 1e-9)
    near = sparse.csr_matrix((np.ones(len(r), bool), (r, c)), shape=shape)
    return g, gz, w, near


def scaled_columns(m: Any, col_scale: np.ndarray, factor: float) -> Any:
    """The CSR matrix ``m`` with column a multiplied by ``col_scale[a]``, then by ``factor`` (new values,
    the index arrays shared)."""
    from scipy import sparse
    m = sparse.csr_matrix(m)
    return sparse.csr_matrix((m.data * np.asarray(col_scale, float)[m.indices] * factor, m.indices, m.indptr),
                             shape=m.shape)


def age_weight(age_ms: ArrayLike | None, tau_ms: float) -> np.ndarray | float:
    """exp(-age / tau) (1 for unknown ages or tau = 0)."""
    if age_ms is None or tau_ms <= 0:
        return 1.0
    a = np.nan_to_num(np.asarray(age_ms, float), nan=0.0)
    return np.exp(-np.maximum(a, 0.0) / tau_ms)


def sorensen(c: np.ndarray, q: np.ndarray, readings: ApReadings, sums: np.ndarray, m: int) -> np.ndarray:
    """Sørensen distance (m,) of a query given as columns c (q,) and values q (q,) to the rows of
    ``readings`` (their value sums ``sums`` (m,))."""
    rows, map_vals, lens = readings.gather(c)
    if len(rows) == 0:
        return np.ones(m)
    mins = np.minimum(np.repeat(q, lens), map_vals)
    shared = np.bincount(rows, weights=mins, minlength=m)
    d = 1.0 - 2.0 * shared / np.maximum(q.sum() + sums, 1e-300)
    return np.clip(d, 0.0, 1.0)
