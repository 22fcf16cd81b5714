"""A radio map that extrapolates: per-AP log-distance path loss as the prior mean of the field.

Kernel regression of the survey scans (:mod:`indoor_loc.wifi.powed_knn`'s interpolated grid) cannot
extrapolate: away from the survey walks it copies the nearest scans, so a user walking where no
survey walk went is matched to the nearest surveyed stretch. The standard remedy is a
Gaussian-process radio map whose *mean function* is a parametric propagation model and whose
residual is interpolated near the data (Ferris, Hähnel & Fox, "Gaussian processes for signal
strength-based location estimation", RSS 2006; Bekkali, Masuo, Tominaga, Nakamura & Matsumoto,
"Gaussian processes for learning-based indoor localization", ICSPCS 2011; Atia, Noureldin & Korenberg,
"Dynamic online-calibrated radio maps for indoor positioning in wireless local area networks",
IEEE TMC 2013). Here:

- **Prior mean:** every AP's log-distance path-loss model ``P = A − 10 n log10(d)`` with its own power
  at 1 m, exponent and position (:class:`indoor_loc.wifi.pathloss.PathLoss`, Nurminen et al. 2014),
  fitted per floor on that floor's map scans.
- **Prior variance:** the model's residual variance σ_a² plus the propagated uncertainty of the AP's
  parameters, ``g^T C_a g`` (g = ∂P/∂θ_a at the point): an AP whose position is poorly known is
  poorly known everywhere, and most of all far from where it was heard.
- **What a fingerprint holds at a point:** the powed value of a reading is 0 below the detection
  floor, so the value expected there is ``E[powed(R)]`` with ``R ~ N(μ, σ²)``:
  it carries the AP's detection probability, ``P(R > floor)``, and an
  AP predicted near the floor with a large variance contributes a small, blurred value instead of a
  hard "heard" or "not heard". The expectation has a closed form in the parabolic cylinder function,
  tabulated once.
- **Posterior (large-noise limit):** at a candidate x the field is the kernel regression of the
  survey scans with the prior as λ = ``field_weight`` pseudo-scans at x::

      v_a(x) = (Σ_i K(x, x_i) v_ia + λ · prior_a(x)) / (Σ_i K(x, x_i) + λ)

  Near the survey walks (kernel mass ≫ λ) this is the interpolated grid; far from them it tends to
  the path-loss prediction. With the Gaussian kernel, λ = 0.05 is the weight of one survey scan
  2.45 bandwidths away (≈ 10 m at 4 m): the data decide within that distance, the propagation model
  beyond it. Scans that did not hear an AP count as 0 in the kernel sum, so a non-detection near
  the survey walks is kept as evidence.

Functions only (no state): the caller owns the candidate grid and the matching.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np
from scipy import sparse
from scipy.special import gamma, pbdv

from indoor_loc.wifi.pathloss import PathLoss, PathLossParams
from indoor_loc.wifi.types import RadioMap

#: the field weight used with a floor plan (``indoor-loc import ms-indoor`` writes it with the plans): the prior
#: weighs as much as one survey scan 10 m away at the 4 m kernel (2.45 bandwidths)
PLAN_FIELD_WEIGHT = 0.05
#: expected powed values below this are dropped (an AP all but undetectable there: a reading of about
#: −92 dBm without AP weights), which keeps the extrapolated grid sparse
FIELD_MIN_VALUE = 1e-3
#: where people can be on a floor: (xy (N, 2) m, floor height z m) -> (N,) bool (e.g. a floor plan's free space)
Walkable = Callable[[np.ndarray, float], np.ndarray]

#: an AP is taken as not heard where its predicted RSS is below this quantile of the map's readings (what
#: the phones report at the weakest: readings below it are rare, so the AP is more likely missed than heard)
DETECT_QUANTILE = 0.05
#: E[max(Z + t, 0)^beta], Z ~ N(0, 1), is tabulated on t in [T_LO, T_HI] (0 below; an asymptotic series above)
T_LO, T_HI, T_STEP = -10.0, 25.0, 0.005


@lru_cache(maxsize=4)
def _positive_part_moment(beta: float) -> tuple[np.ndarray, np.ndarray]:
    """(t, E[max(Z + t, 0)^beta]) on a fine grid of t: Γ(β + 1) e^(−t²/4) D_(−β−1)(−t) / √(2π), with
    D the parabolic cylinder function (Abramowitz & Stegun 19.5.1)."""
    t = np.arange(T_LO, T_HI + T_STEP / 2, T_STEP)
    return t, gamma(beta + 1.0) * np.exp(-0.25 * t * t) * pbdv(-beta - 1.0, -t)[0] / math.sqrt(2.0 * math.pi)


def expected_powed(mu_dbm: np.ndarray, sigma_db: np.ndarray, floor_dbm: float, beta: float) -> np.ndarray:
    """E[powed(R)] for R ~ N(mu, sigma^2) (dBm, dB > 0; broadcast), powed(r) = (max(r − floor, 0) / −floor)^beta:
    (sigma / −floor)^beta · E[max(Z + t, 0)^beta] with t = (mu − floor) / sigma (tabulated; for t above the
    table t^beta (1 + beta (beta − 1) / (2 t²)), relative error below 1e-6)."""
    mu, sig = np.broadcast_arrays(np.asarray(mu_dbm, float), np.asarray(sigma_db, float))
    sig = np.maximum(sig, 1e-9)
    t = (mu - floor_dbm) / sig
    tab_t, tab_m = _positive_part_moment(float(beta))
    x = np.clip((t - T_LO) / T_STEP, 0.0, len(tab_t) - 1.0)     # uniform table: index directly
    i = np.minimum(x.astype(np.int64), len(tab_t) - 2)
    f = x - i
    m = np.where(t < T_LO, 0.0, (1.0 - f) * tab_m[i] + f * tab_m[i + 1])
    hi = t > T_HI
    th = t[hi]
    m[hi] = th ** beta * (1.0 + beta * (beta - 1.0) / (2.0 * th * th))
    return (sig / -floor_dbm) ** beta * m


@dataclass(frozen=True)
class FloorModels:
    """The path-loss models of one floor's APs: ``cols`` (K,) the APs' columns in the radio map, ``theta``
    (K, 4) [A, n, px, py], ``cov`` (K, 4, 4) their covariance, ``sigma2`` (K,) the residual variances."""
    cols: np.ndarray
    theta: np.ndarray
    cov: np.ndarray
    sigma2: np.ndarray
    d0_m: float


def detect_level(radio_map: RadioMap, keep: np.ndarray | None = None) -> float:
    """The map's weakest usual reading (dBm): the ``DETECT_QUANTILE`` of its readings (of the scans ``keep``)."""
    rss = np.asarray(radio_map.rssi_dbm, float)
    if keep is not None:
        rss = rss[np.asarray(keep, bool)]
    heard = rss[np.isfinite(rss)]
    return float(np.quantile(heard, DETECT_QUANTILE)) if len(heard) else -math.inf


def fit_floor_models(radio_map: RadioMap, floors: np.ndarray, *, params: PathLossParams | None = None,
                     keep: np.ndarray | None = None, aps: np.ndarray | None = None) -> dict[float, FloorModels]:
    """Per floor height in ``floors`` the log-distance models of the APs its map scans heard (those with
    enough scans for the fit), fitted on the map scans ``keep`` (M,) bool (all if None). ``aps``
    (n_floors, A) bool, per floor in ``floors``' order: fit only these APs. Each AP's model depends on
    its own readings only, so fitting a subset gives the same models as fitting all."""
    pos = np.asarray(radio_map.positions, float)
    rss = np.asarray(radio_map.rssi_dbm, float)
    map_z = np.asarray(radio_map.z_m, float)
    if keep is not None:
        keep = np.asarray(keep, bool)
        pos, rss, map_z = pos[keep], rss[keep], map_z[keep]
    out: dict[float, FloorModels] = {}
    for f, zf in enumerate(np.asarray(floors, float)):
        on = map_z == zf
        heard = np.any(np.isfinite(rss[on]), axis=0)
        if aps is not None:
            heard &= np.asarray(aps[f], bool)
        cols = np.flatnonzero(heard)
        if not on.any() or len(cols) == 0:
            continue
        sub = RadioMap(positions=pos[on], bssids=[radio_map.bssids[a] for a in cols], rssi_dbm=rss[on][:, cols],
                       freq_mhz=np.zeros(len(cols)))
        pl = PathLoss(params).fit(sub)
        use = np.flatnonzero(pl.usable)
        out[float(zf)] = FloorModels(cols[use], pl.theta[use], pl.theta_cov[use], pl.sigma2[use], pl.params.d0_m)
    return out


def prior_values(models: dict[float, FloorModels], grid_pos: np.ndarray, grid_z: np.ndarray, n_aps: int, *,
                 detect_dbm: float, floor_dbm: float, beta: float, min_value: float = FIELD_MIN_VALUE,
                 chunk: int = 1 << 16) -> sparse.csr_matrix:
    """(C, n_aps) sparse expected powed values of the per-floor ``models`` at the candidates ``grid_pos``
    (C, 2) m on floors ``grid_z`` (C,) m; 0 where the predicted RSS is below ``detect_dbm`` (more likely
    not heard than heard there) or the value below ``min_value``. Evaluated in blocks of about ``chunk``
    (candidate, AP) pairs: blocks that stay in the processor's cache take 40 % less time than blocks of
    2048 candidates, with the same values."""
    grid_pos = np.asarray(grid_pos, float)
    grid_z = np.asarray(grid_z, float)
    # built as CSR directly (int32 columns, no (row, column) pairs): a block's pairs come in row-major order
    # with the columns ascending, so they are the CSR entries of their rows once the rows are in order
    counts = np.zeros(len(grid_pos), np.int64)
    cc: list[np.ndarray] = [np.zeros(0, np.int32)]
    vv: list[np.ndarray] = [np.zeros(0)]
    block_rows: list[np.ndarray] = []
    for zf in np.unique(grid_z):
        fm = models.get(float(zf))
        rows = np.flatnonzero(grid_z == zf)
        if fm is None or len(rows) == 0 or len(fm.cols) == 0:
            continue
        th, s2, d0 = fm.theta, fm.sigma2, fm.d0_m
        a0, n_exp, px, py = th[:, 0], th[:, 1], th[:, 2], th[:, 3]
        cols = fm.cols.astype(np.int32)
        # g^T C g with g = [1, -10 log10 d, k dx, k dy] (k = 10 n / (ln 10 d^2)), C symmetric: its ten
        # distinct entries per AP, the off-diagonal ones doubled
        c = fm.cov
        c00, c11, c22, c33 = c[:, 0, 0], c[:, 1, 1], c[:, 2, 2], c[:, 3, 3]
        c01, c02, c03 = 2.0 * c[:, 0, 1], 2.0 * c[:, 0, 2], 2.0 * c[:, 0, 3]
        c12, c13, c23 = 2.0 * c[:, 1, 2], 2.0 * c[:, 1, 3], 2.0 * c[:, 2, 3]
        base = s2 + c00
        kn = (10.0 / np.log(10.0)) * n_exp
        step = max(1, chunk // len(fm.cols))
        for lo in range(0, len(rows), step):
            r = rows[lo:lo + step]
            dx = grid_pos[r, 0][:, None] - px[None, :]                              # (c, a)
            dy = grid_pos[r, 1][:, None] - py[None, :]
            d2 = dx * dx + dy * dy + d0 * d0
            log10d = 0.5 * np.log10(d2)
            mu = a0[None, :] - 10.0 * n_exp[None, :] * log10d
            flat = np.flatnonzero(mu >= detect_dbm)                              # the pairs it may be heard at
            ci, ai = np.divmod(flat, mu.shape[1])
            g1 = -10.0 * log10d.ravel()[flat]
            k = kn[ai] / d2.ravel()[flat]
            g2 = k * dx.ravel()[flat]
            g3 = k * dy.ravel()[flat]
            var = (base[ai] + g1 * (c01[ai] + c11[ai] * g1 + c12[ai] * g2 + c13[ai] * g3)
                   + g2 * (c02[ai] + c22[ai] * g2 + c23[ai] * g3) + g3 * (c03[ai] + c33[ai] * g3))
            v = expected_powed(mu.ravel()[flat], np.sqrt(var), floor_dbm, beta)
            big = v >= min_value
            counts[r] = np.bincount(ci[big], minlength=len(r))
            block_rows.append(r)
            cc.append(cols[ai[big]])
            vv.append(v[big])
    indptr = np.concatenate([[0], np.cumsum(counts)])
    order = np.concatenate(block_rows) if block_rows else np.zeros(0, np.int64)
    data, indices = np.concatenate(vv), np.concatenate(cc)
    del cc, vv
    if np.any(np.diff(order) < 0):                   # the floors' rows interleave: put the entries in row order
        perm = np.argsort(np.repeat(order, counts[order]), kind="stable")
        data, indices = data[perm], indices[perm]
    return sparse.csr_matrix((data, indices, indptr), shape=(len(grid_pos), n_aps))


def pathloss_prior(radio_map: RadioMap, grid_pos: np.ndarray, grid_z: np.ndarray, *, floor_dbm: float, beta: float,
                   min_value: float = FIELD_MIN_VALUE, params: PathLossParams | None = None,
                   keep: np.ndarray | None = None, detect_dbm: float | None = None,
                   chunk: int = 1 << 16) -> sparse.csr_matrix:
    """(C, A) sparse expected powed values of the map's APs (columns as ``radio_map.bssids``) at the
    candidates ``grid_pos`` (C, 2) m on floors ``grid_z`` (C,) m, from per-floor path-loss models of
    the map scans; values below ``min_value`` (an AP all but undetectable there) are dropped. APs
    with fewer map scans than the path-loss fit needs get no prior (0). ``keep`` (M,) bool: fit on these
    map scans only (a cross-validation fold). ``detect_dbm``: the level below which an AP counts as not
    heard (default :func:`detect_level` of the scans fitted on)."""
    models = fit_floor_models(radio_map, np.unique(np.asarray(grid_z, float)), params=params, keep=keep)
    if detect_dbm is None:
        detect_dbm = detect_level(radio_map, keep)
        if not math.isfinite(detect_dbm):
            detect_dbm = floor_dbm
    return prior_values(models, grid_pos, grid_z, len(radio_map.bssids), detect_dbm=detect_dbm,
                        floor_dbm=floor_dbm, beta=beta, min_value=min_value, chunk=chunk)


def view_scale(values: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """(A,) per-AP factor that maps raw powed values to a view's values (AP weights, mean age weight):
    Σ_i values_ia / Σ_i raw_ia over the map scans (0 for an AP no scan heard)."""
    num = np.asarray(values, float).sum(axis=0)
    den = np.asarray(raw, float).sum(axis=0)
    return np.where(den > 0, num / np.maximum(den, 1e-300), 0.0)


def within_reach(grid_pos: np.ndarray, grid_z: np.ndarray, pos: np.ndarray, z: np.ndarray, reach_m: float) -> np.ndarray:
    """(C,) bool: the candidates within ``reach_m`` of a map scan (``pos`` (M, 2), ``z`` (M,)) of their floor."""
    from scipy.spatial import cKDTree
    out = np.zeros(len(grid_pos), bool)
    for zf in np.unique(grid_z):
        on, rows = z == zf, np.flatnonzero(grid_z == zf)
        if on.any():
            d, _ = cKDTree(pos[on]).query(grid_pos[rows], distance_upper_bound=reach_m + 1e-9)
            out[rows] = np.isfinite(d)
    return out


def walkable_mask(walkable: Walkable, grid_pos: np.ndarray, grid_z: np.ndarray) -> np.ndarray:
    """(C,) bool: ``walkable`` per floor of the candidates."""
    out = np.zeros(len(grid_pos), bool)
    for zf in np.unique(grid_z):
        rows = np.flatnonzero(grid_z == zf)
        out[rows] = np.asarray(walkable(grid_pos[rows], float(zf)), bool)
    return out
