"""Per-vertex Gaussian fingerprint map with linear interpolation along graph edges (Kim et al. 2012).

Each graph vertex p stores, per AP a, a Gaussian of the RSS (mu_pa dBm, sigma_pa^2 dB^2) and a
detection probability pdet_pa. At a point x on edge (i, j) at fraction ``pos`` from i (so
|x - x_i| = pos |x_i - x_j|) the seed's interpolation::

    mu_x = (|x - x_j| mu_i + |x - x_i| mu_j) / |x_i - x_j| = (1 - pos) mu_i + pos mu_j

(the nearer end weighs more) is applied to mu, sigma^2 and pdet alike. The likelihood of a scan
is the product over the APs it heard that the map knows (Kim et al. 2012)::

    p(z | x) = prod_k  pdet_x,k [ (1 - eps) N(z_k | mu_x,k, sigma_x,k^2) + eps / range ]

* ``pdet`` (``use_detection``) handles an AP that is missing at a vertex: near fingerprints that
  never heard it the detection probability is low, so hearing it there is penalised without the
  ``-100 dBm floor value`` trick (whose Gaussian term would swamp every other AP);
* ``eps`` (``outlier_prob``) is a uniform outlier component over ``rssi_range_db`` that bounds
  each AP's contribution (moved APs, body shadowing);
* ``use_non_detections`` adds ``prod (1 - pdet)`` over the map's APs not heard, with
  ``log(1 - pdet)`` interpolated along the edge (log domain, so the per-vertex sums can be
  precomputed). The seed multiplies over the heard APs only (``use_non_detections=False``);
  on PUTMC the non-detections bring the single-scan maximum-likelihood error from 3.1 to 2.6 m,
  so they are on by default. APs unknown to the map are ignored.

Building the vertex models from a :class:`RadioMap` (:meth:`FingerprintGraph.fit`): fingerprints
are assigned to vertices by a Gaussian kernel on the Euclidean distance (``assign="kernel"``) or
to their nearest vertex (``assign="nearest"``). Vertices without data get the kernel-weighted
(i.e. nearest-data) mean with weights renormalised per vertex, a variance shrunk towards the
prior ``prior_sigma_db^2`` by the raw kernel mass plus ``(extrapolation_db_per_m * d_nn)^2``
(d_nn: distance to the nearest fingerprint that heard the AP), and a detection probability
shrunk towards ``det_prior``. :meth:`log_likelihood` is vectorised over particles.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.errors import ConfigError, MapError
from indoor_loc.wifi.types import ApIndex, RadioMap, WifiScan

LOG_SQRT_2PI = 0.5 * np.log(2.0 * np.pi)


@dataclass(frozen=True)
class FingerprintGraphParams:
    """Building and evaluating the per-vertex fingerprint likelihood."""
    assign: str = field("kernel", "fingerprint -> vertex assignment: 'kernel' or 'nearest'")
    kernel_sigma_m: float = field(2.0, "Gaussian kernel std for assignment and for filling empty vertices (m)")
    prior_sigma_db: float = field(4.0, "prior RSS std at a vertex (dB)")
    sigma_nu0: float = field(2.0, "pseudo-observations of the prior std")
    min_sigma_db: float = field(2.0, "lower bound of a vertex RSS std (dB)")
    extrapolation_db_per_m: float = field(1.0, "std added per metre to the nearest fingerprint that heard the AP (dB/m)")
    det_prior: float = field(0.5, "prior detection probability of an AP at a vertex")
    det_prior_weight: float = field(1.0, "pseudo-observations of det_prior")
    use_detection: bool = field(True, "multiply each heard AP's term by its detection probability")
    use_non_detections: bool = field(True, "multiply by (1 - pdet) for the map's APs not heard")
    outlier_prob: float = field(0.05, "weight eps of the uniform outlier component per AP")
    rssi_range_db: float = field(100.0, "width of the uniform outlier density (dB)")
    min_signal_dbm: float = field(-100.0, "readings below this (dBm) are ignored")

    def validate(self) -> None:
        n = type(self).__name__
        require(self.assign in ("kernel", "nearest"), n, "assign", "'kernel' or 'nearest'", self.assign)
        for name in ("kernel_sigma_m", "prior_sigma_db", "sigma_nu0", "min_sigma_db", "det_prior_weight",
                     "rssi_range_db"):
            require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        require(self.extrapolation_db_per_m >= 0, n, "extrapolation_db_per_m", ">= 0", self.extrapolation_db_per_m)
        require(0.0 < self.det_prior < 1.0, n, "det_prior", "in (0, 1)", self.det_prior)
        require(0.0 <= self.outlier_prob < 1.0, n, "outlier_prob", "in [0, 1)", self.outlier_prob)


class FingerprintGraph:
    """Per-vertex RSS Gaussians on a graph and the interpolated scan likelihood for particles.

    After :meth:`fit`: ``mu`` (V, A) dBm, ``var`` (V, A) dB^2, ``pdet`` (V, A), ``bssids`` (A,),
    ``node_xy`` (V, 2) m, ``link_nodes`` (L, 2).
    """

    def __init__(self, params: FingerprintGraphParams | None = None) -> None:
        self.params = params or FingerprintGraphParams()
        self.params.validate()
        self.aps = ApIndex()
        self.node_xy = np.zeros((0, 2))
        self.link_nodes = np.zeros((0, 2), np.int64)
        self.mu = np.zeros((0, 0))
        self.var = np.zeros((0, 0))
        self.pdet = np.zeros((0, 0))
        self._log_miss = np.zeros((0, 0))
        self._log_miss_sum = np.zeros(0)

    @property
    def bssids(self) -> list[str]:
        """The APs (column order) this method knows."""
        return self.aps.bssids

    def fit(self, radio_map: RadioMap, node_xy: np.ndarray, link_nodes: np.ndarray) -> "FingerprintGraph":
        """Build the vertex models. node_xy (V, 2) or (V, 3) m (only x, y are used: one floor);
        link_nodes (L, 2) vertex indices of each edge."""
        p = self.params
        node_xy = np.asarray(node_xy, float)
        link_nodes = np.asarray(link_nodes)
        if node_xy.ndim != 2 or node_xy.shape[1] not in (2, 3) or len(node_xy) == 0:
            raise MapError(f"fingerprint graph: expected node_xy (V, 2|3), V > 0, got {node_xy.shape}")
        if link_nodes.ndim != 2 or link_nodes.shape[1] != 2 or (link_nodes.size and (
                link_nodes.min() < 0 or link_nodes.max() >= len(node_xy))):
            raise MapError(f"fingerprint graph: expected link_nodes (L, 2) indexing {len(node_xy)} vertices, "
                           f"got shape {link_nodes.shape}")
        pos = np.asarray(radio_map.positions, float)
        rss = np.asarray(radio_map.rssi_dbm, float)
        if pos.ndim != 2 or pos.shape[1] != 2 or rss.shape != (len(pos), len(radio_map.bssids)) or len(pos) == 0:
            raise MapError(f"fingerprint graph: radio map expected positions (M, 2), M > 0, and rssi (M, A), got "
                           f"{pos.shape}, {rss.shape}")
        self.node_xy = node_xy[:, :2].copy()
        self.link_nodes = link_nodes.astype(np.int64)
        self.aps = ApIndex(radio_map.bssids)
        V, (M, A) = len(node_xy), rss.shape
        heard = np.isfinite(rss) & (np.nan_to_num(rss, nan=-999.0) >= p.min_signal_dbm)
        z = np.where(heard, rss, 0.0)
        d2 = ((self.node_xy[:, None, :] - pos[None, :, :]) ** 2).sum(-1)  # (V, M)
        logw = -0.5 * d2 / p.kernel_sigma_m ** 2
        if p.assign == "nearest":
            owner = np.argmin(d2, axis=0)  # nearest vertex of each fingerprint
            assigned = np.zeros((V, M), bool)
            assigned[owner, np.arange(M)] = True
            # assigned fingerprints have weight 1; the kernel only fills vertices without data
            logw = np.where(assigned, 0.0, logw - 1e3)
        w_all = np.exp(logw).sum(1)  # raw mass of every fingerprint at each vertex (V,)
        self.mu = np.empty((V, A))
        self.var = np.empty((V, A))
        self.pdet = np.empty((V, A))
        for a in range(A):  # (V, M) work per AP keeps memory at V*M for large maps
            h = heard[:, a]
            if not h.any():
                self.mu[:, a] = p.min_signal_dbm
                self.var[:, a] = p.prior_sigma_db ** 2
                self.pdet[:, a] = p.det_prior * p.det_prior_weight / (w_all + p.det_prior_weight)
                continue
            la = logw[:, h]
            mx = la.max(axis=1, keepdims=True)
            wr = np.exp(la - mx)  # renormalised per vertex: nearest data dominates far from data
            za = z[h, a]
            mu = wr @ za / wr.sum(1)
            raw = np.exp(la)  # raw kernel mass: how much data there is near the vertex
            ss = (raw * (za[None, :] - mu[:, None]) ** 2).sum(1)
            mass = raw.sum(1)
            var = (ss + p.sigma_nu0 * p.prior_sigma_db ** 2) / (mass + p.sigma_nu0)
            d_nn2 = np.min(d2[:, h], axis=1)
            var = np.maximum(var, p.min_sigma_db ** 2) + p.extrapolation_db_per_m ** 2 * d_nn2
            self.mu[:, a] = mu
            self.var[:, a] = var
            self.pdet[:, a] = (mass + p.det_prior * p.det_prior_weight) / (w_all + p.det_prior_weight)
        self._log_miss = np.log1p(-np.minimum(self.pdet, 1.0 - 1e-9))  # log(1 - pdet) (V, A)
        self._log_miss_sum = self._log_miss.sum(axis=1)
        return self

    # ------------------------------------------------------------------------------------------
    def interpolate(self, link: np.ndarray, pos: np.ndarray, cols: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """mu, sigma^2, pdet at points (link (N,), pos (N,) in [0, 1] from the link's first vertex)
        for AP columns ``cols`` (K,) (all if None) -> three (N, K) arrays (Kim et al. 2012)."""
        link = np.asarray(link, np.int64)
        t = np.clip(np.asarray(pos, float), 0.0, 1.0)[:, None]
        if link.shape != t.shape[:1]:
            raise ConfigError(f"fingerprint graph: expected link (N,) and pos (N,), got {link.shape}, {t.shape[:1]}")
        if link.size and (link.min() < 0 or link.max() >= len(self.link_nodes)):
            raise ConfigError(f"fingerprint graph: link index out of range [0, {len(self.link_nodes)})")
        cols = np.arange(len(self.bssids)) if cols is None else np.asarray(cols, np.int64)
        i, j = self.link_nodes[link, 0], self.link_nodes[link, 1]
        out = []
        for tab in (self.mu, self.var, self.pdet):
            tk = tab[:, cols]
            out.append((1.0 - t) * tk[i] + t * tk[j])
        return out[0], out[1], out[2]

    def scan_columns(self, scan: WifiScan) -> tuple[np.ndarray, np.ndarray]:
        """(map column index (K,), rssi (K,)) of the scan's readings the map knows."""
        r = np.asarray(scan.rssi_dbm, float)
        idx = self.aps.columns(scan.bssid)
        keep = (idx >= 0) & np.isfinite(r) & (r >= self.params.min_signal_dbm)
        return idx[keep], r[keep]

    def log_likelihood(self, link: np.ndarray, pos: np.ndarray, scan: WifiScan) -> np.ndarray:
        """log p(scan | particle) for particles on links (link (N,) int, pos (N,) in [0, 1]) -> (N,).

        Returns zeros (no information) when the scan has no AP the map knows.
        """
        p = self.params
        if not self.bssids:
            raise MapError("fingerprint graph: fit() it before asking for likelihoods")
        cols, z = self.scan_columns(scan)
        link = np.asarray(link, np.int64)
        if len(cols) == 0:
            return np.zeros(len(link))
        mu, var, pdet = self.interpolate(link, pos, cols)
        gauss = np.exp(-0.5 * (z - mu) ** 2 / var - 0.5 * np.log(var) - LOG_SQRT_2PI)
        term = (1.0 - p.outlier_prob) * gauss + p.outlier_prob / p.rssi_range_db
        if p.use_detection:
            term = term * pdet
        ll = np.log(term).sum(axis=1)
        if p.use_non_detections:
            # sum over the map's APs not heard of log(1 - pdet), interpolated in the log domain as
            # (all APs) - (heard APs) so the cost is O(N K), not O(N A)
            t = np.clip(np.asarray(pos, float), 0.0, 1.0)
            i, j = self.link_nodes[link, 0], self.link_nodes[link, 1]
            tot = (1.0 - t) * self._log_miss_sum[i] + t * self._log_miss_sum[j]
            lm = self._log_miss[:, cols]
            heard = ((1.0 - t)[:, None] * lm[i] + t[:, None] * lm[j]).sum(axis=1)
            ll = ll + tot - heard
        return ll

    def link_point(self, link: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Map positions (N, 2) m of points on links."""
        link = np.asarray(link, np.int64)
        t = np.clip(np.asarray(pos, float), 0.0, 1.0)[:, None]
        a, b = self.node_xy[self.link_nodes[link, 0]], self.node_xy[self.link_nodes[link, 1]]
        return (1.0 - t) * a + t * b
