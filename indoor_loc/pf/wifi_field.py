"""WiFi scan likelihood on the graph's links: the radio map's fingerprints interpolated along links.

The particle filter can weigh particles with a WiFi scan directly instead of with a position fix
(Koivisto et al., "Graph-based map matching for indoor positioning", IPIN 2014, where fingerprints
sit at graph points and a particle's fingerprint is interpolated along its link). Here:

- every link is cut into pieces of at most ``spacing_m``; at each cut point the expected RSS of
  every AP is the Gaussian-kernel average (bandwidth ``kernel_m``) of the radio map's readings of
  that AP on the same floor; a point with too little kernel weight from readings of an AP
  (``min_weight``) expects the AP at ``missing_dbm`` (not heard there);
- a particle at fraction ``f`` between cut points ``i`` and ``i + 1`` expects
  ``μ = (1 − f) μ_i + f μ_{i+1}`` (linear interpolation along the link);
- the scan's ``max_aps`` strongest APs known to the map give
  ``log L = Σ_k log((1 − ε) N(r_k | μ_k, σ²) + ε / 100 dB)`` (an outlier mixture per reading,
  ``ε = outlier_prob``), scaled by ``1 / temper`` (readings of one scan are not independent).

Everything is vectorised: ``(N, K)`` arrays per scan, ``K ≤ max_aps``. :meth:`sample_points` draws
positions in proportion to a scan's likelihood (initialisation and sensor resetting).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.spatial import cKDTree

from indoor_loc import params as P
from indoor_loc.errors import InvalidInputError, MapError
from indoor_loc.graph.model import BuildingGraph
from indoor_loc.wifi.types import ApIndex, RadioMap, WifiScan


@dataclass(frozen=True)
class ScanFieldParams:
    """WiFi scan likelihood on the links (see :mod:`indoor_loc.pf.wifi_field`)."""
    spacing_m: float = P.field(1.0, "fingerprints are interpolated between points at most this far apart along a link (m)")
    kernel_m: float = P.field(2.0, "Gaussian kernel bandwidth averaging the radio map's readings at each link point (m)")
    min_weight: float = P.field(0.05, "kernel weight of an AP's readings below which a link point expects it unheard")
    missing_dbm: float = P.field(-100.0, "RSS expected where an AP is not heard (dBm)")
    sigma_db: float = P.field(6.0, "RSS deviation from the interpolated fingerprint (dB)")
    outlier_prob: float = P.field(0.05, "probability that a reading is an outlier (uniform over 100 dB)")
    max_aps: int = P.field(10, "the strongest this many APs of a scan that the map knows are used")
    temper: float = P.field(3.0, "the scan's log-likelihood is divided by this (correlated readings)")
    floor_tol_m: float = P.field(1.5, "radio map readings count for a link point within this height (m)")

    def validate(self) -> None:
        n = type(self).__name__
        for name in ("spacing_m", "kernel_m", "sigma_db", "temper", "floor_tol_m"):
            P.require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        P.require(self.min_weight >= 0, n, "min_weight", ">= 0", self.min_weight)
        P.require(0 < self.outlier_prob < 1, n, "outlier_prob", "in (0, 1)", self.outlier_prob)
        P.require(self.max_aps >= 1, n, "max_aps", ">= 1", self.max_aps)


class EdgeFingerprintField:
    """Expected RSS at points along every link and the scan log-likelihood of particles."""

    def __init__(self, graph: BuildingGraph, radio_map: RadioMap, params: ScanFieldParams | None = None,
                 *, chunk: int = 2048) -> None:
        self.params = params or ScanFieldParams()
        self.params.validate()
        pp = self.params
        rm = radio_map
        if len(rm.positions) == 0 or len(rm.bssids) == 0:
            raise MapError("scan likelihood: the radio map has no fingerprints")
        self.g = graph
        self.aps = ApIndex(rm.bssids)
        length = graph.link_len.astype(float)
        self.n_seg = np.maximum(np.ceil(length / pp.spacing_m).astype(np.int64), 1)
        per = self.n_seg + 1
        self.ptr = np.concatenate([[0], np.cumsum(per)[:-1]]).astype(np.int64)
        link = np.repeat(np.arange(graph.n_links), per)
        frac = (np.arange(len(link)) - np.repeat(self.ptr, per)) / self.n_seg[link]
        xyz = graph.node_xyz
        a, b = xyz[graph.link_nodes[link, 0]], xyz[graph.link_nodes[link, 1]]
        pts = a + frac[:, None] * (b - a)                                    # (S, 3)
        self.points = pts[:, :2]
        # kernel average of every AP's readings at every link point (same floor only)
        heard = np.isfinite(rm.rssi_dbm)
        vals = np.where(heard, rm.rssi_dbm, 0.0)
        tree = cKDTree(rm.positions)
        mu = np.full((len(pts), len(rm.bssids)), pp.missing_dbm)
        radius = 3.0 * pp.kernel_m
        for s in range(0, len(pts), chunk):
            q = pts[s:s + chunk]
            near = tree.query_ball_point(q[:, :2], radius)
            rows = np.concatenate([np.full(len(nb), i) for i, nb in enumerate(near)]).astype(np.int64) if len(q) else np.zeros(0, np.int64)
            cols = np.concatenate([np.asarray(nb, np.int64) for nb in near]) if len(q) else np.zeros(0, np.int64)
            if len(cols) == 0:
                continue
            d2 = ((q[rows, :2] - rm.positions[cols]) ** 2).sum(axis=1)
            same_floor = np.abs(q[rows, 2] - rm.z_m[cols]) <= pp.floor_tol_m
            w = np.where(same_floor, np.exp(-0.5 * d2 / pp.kernel_m ** 2), 0.0)
            W = csr_matrix((w, (rows, cols)), shape=(len(q), len(rm.positions)))
            wsum = np.asarray(W @ heard.astype(float))                       # (q, A)
            vsum = np.asarray(W @ vals)
            ok = (wsum > 0) & (wsum >= pp.min_weight)
            mu[s:s + chunk][ok] = vsum[ok] / wsum[ok]
        self.mu = mu                                                         # (S, A) dBm

    @property
    def n_points(self) -> int:
        return len(self.points)

    def _columns(self, scan: WifiScan) -> tuple[np.ndarray, np.ndarray]:
        """Map columns and readings of the scan's ``max_aps`` strongest APs the map knows."""
        if len(scan) == 0:
            raise InvalidInputError("empty_scan", "scan likelihood: the scan has no APs")
        cols = self.aps.columns(scan.bssid)
        rss = np.asarray(scan.rssi_dbm, float)
        known = cols >= 0
        cols, rss = cols[known], rss[known]
        order = np.argsort(-rss, kind="stable")[:self.params.max_aps]
        return cols[order], rss[order]

    def _log_lik(self, mu: np.ndarray, rss: np.ndarray) -> np.ndarray:
        pp = self.params
        z = (rss - mu) / pp.sigma_db
        g = np.exp(-0.5 * z * z) / (np.sqrt(2 * np.pi) * pp.sigma_db)
        return np.log((1.0 - pp.outlier_prob) * g + pp.outlier_prob / 100.0).sum(axis=-1) / pp.temper

    def known_aps(self, scan: WifiScan) -> int:
        """How many of the scan's APs the radio map knows (0: the scan carries no information)."""
        return int((self.aps.columns(scan.bssid) >= 0).sum())

    def log_likelihood(self, link: np.ndarray, pos: np.ndarray, scan: WifiScan) -> np.ndarray:
        """(N,) log-likelihood of ``scan`` for particles at ``pos`` metres along ``link``
        (zeros when the map knows none of the scan's APs)."""
        cols, rss = self._columns(scan)
        if len(cols) == 0:
            return np.zeros(len(link))
        length = self.g.link_len[link]
        nseg = self.n_seg[link]
        u = np.divide(pos, length, out=np.zeros(len(link)), where=length > 0) * nseg
        j = np.clip(np.floor(u).astype(np.int64), 0, nseg - 1)
        f = (u - j)[:, None]
        i0 = self.ptr[link] + j
        mu = (1.0 - f) * self.mu[i0[:, None], cols[None, :]] + f * self.mu[i0[:, None] + 1, cols[None, :]]
        return self._log_lik(mu, rss)

    def point_log_likelihood(self, scan: WifiScan) -> np.ndarray:
        """(S,) log-likelihood of ``scan`` at every link point (for initialisation)."""
        cols, rss = self._columns(scan)
        if len(cols) == 0:
            return np.zeros(self.n_points)
        return self._log_lik(self.mu[:, cols], rss)

    def sample_points(self, scan: WifiScan, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n`` positions (link, t in [0, 1]) drawn over the link points in proportion to the
        scan's likelihood there, jittered uniformly over ± half a piece along the link."""
        ll = self.point_log_likelihood(scan)
        w = np.exp(ll - ll.max())
        idx = rng.choice(len(w), size=n, p=w / w.sum())
        link = np.searchsorted(self.ptr, idx, side="right") - 1
        t = (idx - self.ptr[link] + rng.uniform(-0.5, 0.5, n)) / self.n_seg[link]
        return link.astype(np.int32), np.clip(t, 0.0, 1.0)
