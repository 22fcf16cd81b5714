"""Coverage-area (CA) WiFi positioning with the modifications of Raitoharju et al. 2015, Sec. 3.

Each AP i has a Gaussian coverage area N(mu_i, Sigma_i) built from the n_i fingerprint positions
z_ij where it was heard (eqs. 26–27, prior covariance B)::

    mu_i = sum_j z_ij / n_i,   Sigma_i = (sum_j z_ij z_ij^T + B - n_i mu_i mu_i^T) / (n_i + 1)

kept as sufficient statistics so a new fingerprint updates it recursively (eqs. 28–29,
:meth:`CoverageArea.add_fingerprint`). Two levels: a *weak* CA from every fingerprint (B = 100^2 I)
and a *strong* CA from fingerprints with RSS >= -60 dBm (B = 20^2 I); a reading >= -60 dBm uses the
AP's strong CA when it has one. The static estimate of a scan (eqs. 30–31)::

    Sigma_hat = (sum_i Sigma_i^-1)^-1,   mu_hat = Sigma_hat sum_i Sigma_i^-1 mu_i

is returned as ``Fix(xy=mu_hat, cov=Sigma_hat)`` — the linear measurement of eq. 32. The three
modifications are applied in the paper's order and can be switched off for the ablation:

1. minimum size (eqs. 33–34): eigenvalues clipped from below at sigma_min^2 (40^2 weak, 5^2 strong);
2. outlier removal (eqs. 35–37): while max_i (mu_i - mu_hat)^T Sigma_i^-1 (mu_i - mu_hat) > 5.9915
   drop the worst CA and down-date the information sums; when only two mutually distant CAs are
   left the scan is dropped (``ok=False, reason="outlier_conflict"``);
3. MIMO compensation (eqs. 39–40): ``Sigma_i <- [sum_j max(2 - W_ij, 0)] Sigma_i`` with
   ``W_ij = det((Sigma_i + Sigma_j)/2 + d d^T) / sqrt(det Sigma_i det Sigma_j)``, d = mu_i - mu_j.

Everything per scan is vectorised over the received APs (2x2 inverses and determinants in closed
form); the only loop is the one-CA-at-a-time outlier removal the paper prescribes.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.errors import InvalidInputError, MapError
from indoor_loc.measurements import Fix
from indoor_loc.wifi.types import ApIndex, Positioner, RadioMap, WifiScan


@dataclass(frozen=True)
class CoverageParams:
    """Coverage-area positioning (Raitoharju et al. 2015, Sec. 3). The four booleans are the paper's ablation switches."""
    two_level: bool = field(True, "use strong CAs (RSS >= strong_rssi_dbm) beside the weak ones")
    min_size: bool = field(True, "impose a minimum CA variance along the main axes (eq. 34)")
    outlier_removal: bool = field(True, "Mahalanobis outlier removal with down-dating (eqs. 35-37)")
    mimo: bool = field(True, "MIMO / similar-CA compensation of the CA covariances (eqs. 39-40)")
    strong_rssi_dbm: float = field(-60.0, "RSS threshold of the strong level (dBm)")
    prior_weak_m2: float = field(100.0 ** 2, "prior B of weak CAs, per axis (m^2)")
    prior_strong_m2: float = field(20.0 ** 2, "prior B of strong CAs, per axis (m^2)")
    sigma_min_weak_m2: float = field(40.0 ** 2, "minimum variance of weak CAs along main axes (m^2)")
    sigma_min_strong_m2: float = field(5.0 ** 2, "minimum variance of strong CAs along main axes (m^2)")
    outlier_chi2: float = field(5.9915, "squared-Mahalanobis outlier threshold, chi2_2(0.95)")
    min_signal_dbm: float = field(-100.0, "readings below this (dBm) are ignored in map and scans")

    def validate(self) -> None:
        n = type(self).__name__
        for name in ("prior_weak_m2", "prior_strong_m2", "sigma_min_weak_m2", "sigma_min_strong_m2", "outlier_chi2"):
            require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        require(-120.0 <= self.strong_rssi_dbm <= 0.0, n, "strong_rssi_dbm", "in [-120, 0] dBm",
                  self.strong_rssi_dbm)
        require(-120.0 <= self.min_signal_dbm <= 0.0, n, "min_signal_dbm", "in [-120, 0] dBm", self.min_signal_dbm)


@dataclass
class CaLevel:
    """Sufficient statistics of one CA level for A APs: count n (A,), sum of positions s1 (A, 2),
    sum of outer products s2 (A, 2, 2), prior B (m^2 per axis)."""
    n: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    prior_m2: float

    @classmethod
    def empty(cls, n_aps: int, prior_m2: float) -> "CaLevel":
        return cls(np.zeros(n_aps, np.int64), np.zeros((n_aps, 2)), np.zeros((n_aps, 2, 2)), prior_m2)

    def grow(self, n_aps: int) -> None:
        k = n_aps - len(self.n)
        if k > 0:
            self.n = np.r_[self.n, np.zeros(k, np.int64)]
            self.s1 = np.vstack([self.s1, np.zeros((k, 2))])
            self.s2 = np.concatenate([self.s2, np.zeros((k, 2, 2))])

    def mean_cov(self) -> tuple[np.ndarray, np.ndarray]:
        """Eqs. 26–27 for every AP: mu (A, 2) and Sigma (A, 2, 2) (NaN mean where n = 0)."""
        n = self.n.astype(float)
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = self.s1 / n[:, None]
        mm = np.einsum("ai,aj->aij", np.nan_to_num(mu), np.nan_to_num(mu))
        cov = (self.s2 + self.prior_m2 * np.eye(2) - n[:, None, None] * mm) / (n + 1.0)[:, None, None]
        return mu, cov


def _inv2(S: np.ndarray) -> np.ndarray:
    """Inverse of (..., 2, 2) matrices in closed form."""
    det = S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]
    out = np.empty_like(S)
    out[..., 0, 0] = S[..., 1, 1]
    out[..., 1, 1] = S[..., 0, 0]
    out[..., 0, 1] = -S[..., 0, 1]
    out[..., 1, 0] = -S[..., 1, 0]
    return out / det[..., None, None]


def _det2(S: np.ndarray) -> np.ndarray:
    return S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0]


def min_size(cov: np.ndarray, var_min: np.ndarray) -> np.ndarray:
    """Eq. 34: ``V max(Lambda, sigma_min^2 I) V^T`` for covs (K, 2, 2), var_min (K,) m^2."""
    lam, V = np.linalg.eigh(cov)
    lam = np.maximum(lam, np.asarray(var_min, float)[:, None])
    return np.einsum("kij,kj,klj->kil", V, lam, V)


def mimo_factors(mu: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Eqs. 39–40: the factor ``sum_j max(2 - W_ij, 0)`` (K,) by which each CA covariance is scaled."""
    d = mu[:, None, :] - mu[None, :, :]  # (K, K, 2)
    M = 0.5 * (cov[:, None] + cov[None, :]) + np.einsum("ijk,ijl->ijkl", d, d)
    dets = _det2(cov)
    W = _det2(M) / np.sqrt(dets[:, None] * dets[None, :])
    return np.maximum(2.0 - W, 0.0).sum(axis=1)


def fuse(mu: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eqs. 30–31: information-weighted fusion of K Gaussians -> (mu_hat (2,), Sigma_hat (2, 2))."""
    info = _inv2(cov)
    Lam = info.sum(axis=0)
    eta = np.einsum("kij,kj->i", info, mu)
    Sig = _inv2(Lam)
    return Sig @ eta, Sig


class CoverageArea(Positioner):
    """Two-level coverage-area positioning with minimum size, outlier removal and MIMO compensation."""
    name = "coverage"

    def __init__(self, params: CoverageParams | None = None) -> None:
        self.params = params or CoverageParams()
        self.params.validate()
        self.aps = ApIndex()
        self.weak = CaLevel.empty(0, self.params.prior_weak_m2)
        self.strong = CaLevel.empty(0, self.params.prior_strong_m2)
        self._cache: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------------------------------------
    # Radio map
    # ------------------------------------------------------------------------------------------
    @property
    def bssids(self) -> list[str]:
        """The APs (column order) this method knows."""
        return self.aps.bssids

    def fit(self, radio_map: RadioMap) -> "CoverageArea":
        """Build both CA levels from a radio map (eqs. 26–27, vectorised over APs)."""
        pos = np.asarray(radio_map.positions, float)
        rss = np.asarray(radio_map.rssi_dbm, float)
        if pos.ndim != 2 or pos.shape[1] != 2 or rss.shape != (len(pos), len(radio_map.bssids)):
            raise MapError(f"coverage: radio map expected positions (M, 2) and rssi (M, A), got {pos.shape}, {rss.shape}")
        self.aps = ApIndex(radio_map.bssids)
        A = len(self.bssids)
        self.weak = CaLevel.empty(A, self.params.prior_weak_m2)
        self.strong = CaLevel.empty(A, self.params.prior_strong_m2)
        heard = np.isfinite(rss) & (np.nan_to_num(rss, nan=-999.0) >= self.params.min_signal_dbm)
        strong = heard & (np.nan_to_num(rss, nan=-999.0) >= self.params.strong_rssi_dbm)
        zz = np.einsum("mi,mj->mij", pos, pos)
        for lev, mask in ((self.weak, heard), (self.strong, strong)):
            w = mask.astype(float)  # (M, A)
            lev.n = mask.sum(axis=0).astype(np.int64)
            lev.s1 = w.T @ pos
            lev.s2 = np.einsum("ma,mij->aij", w, zz)
        self._cache = None
        return self

    def add_fingerprint(self, xy: np.ndarray, scan: WifiScan) -> None:
        """Grow the map with a fingerprint at ``xy`` (2,) m: the recursive update of eqs. 28–29 for
        every AP heard (new BSSIDs get new CAs)."""
        xy = np.asarray(xy, float).reshape(2)
        if not np.all(np.isfinite(xy)):
            raise InvalidInputError("nan", f"coverage.add_fingerprint: expected a finite position, got {xy}")
        idx = np.array([self.aps.add(b) for b in scan.bssid], dtype=np.int64)
        A = len(self.bssids)
        self.weak.grow(A)
        self.strong.grow(A)
        r = np.asarray(scan.rssi_dbm, float)
        ok = np.isfinite(r) & (r >= self.params.min_signal_dbm)
        for lev, sel in ((self.weak, ok), (self.strong, ok & (r >= self.params.strong_rssi_dbm))):
            j = idx[sel]
            lev.n[j] += 1
            lev.s1[j] += xy
            lev.s2[j] += np.outer(xy, xy)
        self._cache = None

    def coverage_areas(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(mu_weak (A,2), cov_weak (A,2,2), mu_strong, cov_strong) — eqs. 26–27; cached."""
        if self._cache is None:
            self._cache = (*self.weak.mean_cov(), *self.strong.mean_cov())
        return self._cache

    # ------------------------------------------------------------------------------------------
    # Positioning
    # ------------------------------------------------------------------------------------------
    def select(self, scan: WifiScan) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The CAs a scan uses: (ap index (K,), strong level? (K,) bool, mu (K,2), cov (K,2,2)),
        after the minimum-size step when enabled."""
        p = self.params
        r = np.asarray(scan.rssi_dbm, float)
        idx = self.aps.columns(scan.bssid)
        keep = (idx >= 0) & np.isfinite(r) & (r >= p.min_signal_dbm)
        idx, r = idx[keep], r[keep]
        keep = self.weak.n[idx] > 0
        idx, r = idx[keep], r[keep]
        mu_w, cov_w, mu_s, cov_s = self.coverage_areas()
        strong = np.zeros(len(idx), bool)
        if p.two_level:
            strong = (r >= p.strong_rssi_dbm) & (self.strong.n[idx] > 0)
        mu = np.where(strong[:, None], mu_s[idx], mu_w[idx])
        cov = np.where(strong[:, None, None], cov_s[idx], cov_w[idx])
        if p.min_size and len(idx):
            cov = min_size(cov, np.where(strong, p.sigma_min_strong_m2, p.sigma_min_weak_m2))
        return idx, strong, mu, cov

    def locate(self, scan: WifiScan) -> Fix:
        """Static CA estimate of one scan (eqs. 30–31 with the enabled modifications)."""
        nan2, big = np.full(2, np.nan), np.full((2, 2), np.nan)
        if len(scan) == 0:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="empty_scan")
        if not self.bssids:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="no_map")
        idx, strong, mu, cov = self.select(scan)
        if len(idx) == 0:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="no_known_ap")
        active = np.ones(len(idx), bool)
        if self.params.outlier_removal and len(idx) >= 2:
            active, ok = self._remove_outliers(mu, cov)
            if not ok:
                return Fix(scan.stamp_ns, nan2, big, ok=False, reason="outlier_conflict",
                           info={"n_aps": int(len(idx))})
        mu_a, cov_a = mu[active], cov[active]
        factors = np.ones(len(mu_a))
        if self.params.mimo and len(mu_a) >= 2:
            factors = mimo_factors(mu_a, cov_a)
            cov_a = cov_a * factors[:, None, None]
        xy, S = fuse(mu_a, cov_a)
        S = 0.5 * (S + S.T)
        info = {"n_aps": int(len(idx)), "n_used": int(active.sum()), "n_outliers": int((~active).sum()),
                "n_strong": int(strong[active].sum()), "mimo_factors": factors,
                "bssids": [self.bssids[i] for i in idx[active]]}
        return Fix(scan.stamp_ns, xy, S, info=info)

    def _remove_outliers(self, mu: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, bool]:
        """Eqs. 35–37: drop the CA with the largest d_i until all d_i <= threshold, down-dating the
        information sums. Returns (active mask, usable); unusable when two distant CAs remain."""
        thr = self.params.outlier_chi2
        info = _inv2(cov)
        Lam = info.sum(axis=0)
        eta = np.einsum("kij,kj->i", info, mu)
        active = np.ones(len(mu), bool)
        while True:
            m = _inv2(Lam) @ eta
            d = mu - m
            di = np.einsum("ki,kij,kj->k", d, info, d)
            di[~active] = -np.inf
            j = int(np.argmax(di))
            if di[j] <= thr:
                return active, True
            if active.sum() <= 2:
                return active, False
            active[j] = False
            Lam = Lam - info[j]  # eq. 36
            eta = eta - info[j] @ mu[j]  # eq. 37 in information form
