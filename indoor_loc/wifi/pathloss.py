"""Log-distance path-loss WiFi positioning (Nurminen et al. 2014).

Per AP a the received power at position r (m) is modelled as::

    P = A_a - 10 n_a log10(d) + w,   d = sqrt(|r - p_a|^2 + d0^2),   w ~ N(0, sigma_a^2)

with A_a the power at 1 m (dBm), n_a the path-loss exponent and p_a the AP position (m). ``d0``
(default 1 m, the AP's height above the phone) keeps the model finite at the AP. Fitting
(:meth:`PathLoss.fit`) is a Levenberg–Marquardt-damped Gauss–Newton on theta_a = [A, n, px, py]
for all APs at once (batched 4x4 normal equations) with Gaussian priors on A and n and a weak
prior on the AP position around its initial guess (the centroid of the strongest fingerprints),
so an AP heard in a handful of scans stays put instead of flying away. The noise variance is a
shrinkage estimate ``(sum r^2 + nu0 sigma0^2) / (dof + nu0)`` and the parameter covariance
``C_a = (J^T J / sigma_a^2 + prior information)^-1`` is kept.

Positioning (:meth:`PathLoss.locate`) runs Gauss–Newton from several starts at once (the estimated
positions of the APs with the strongest readings and their power-weighted centroid — no WKNN)
and keeps the start with the least cost. Each reading's variance is ``sigma_a^2 + g^T C_a g``
(g = d h / d theta_a at r): the map-parameter uncertainty is propagated, so the returned
covariance ``(J^T W J)^-1`` is honest for the model; it is further inflated by the reduced
chi-square of the fit when that exceeds 1. Real buildings break the model in ways the residuals do
not show (walls: shadowing that is the same at the map and at the user), so an isotropic
``model_error_m^2 I`` is added; its 2 m default was chosen on PUTMC (there the pure model covariance
holds the truth in its 95 % ellipse only 61 % of the time, with 2 m 89 %); set 0 for the pure
Laplace covariance.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from indoor_loc.params import field, require
from indoor_loc.errors import MapError
from indoor_loc.measurements import Fix
from indoor_loc.wifi.types import ApIndex, Positioner, RadioMap, WifiScan

LN10 = np.log(10.0)


@dataclass(frozen=True)
class PathLossParams:
    """Path-loss model fitting and positioning parameters."""
    sigma_db: float = field(4.0, "prior RSS noise std sigma0 (dB); per-AP sigma is shrunk towards it")
    sigma_nu0: float = field(4.0, "pseudo-observations of the sigma0 prior in the per-AP noise estimate")
    d0_m: float = field(1.0, "height offset of the APs; distance d = sqrt(horizontal^2 + d0^2) (m)")
    prior_A_dbm: float = field(-40.0, "prior mean of A, the RSS at 1 m (dBm)")
    prior_A_std_db: float = field(15.0, "prior std of A (dB)")
    prior_n: float = field(2.5, "prior mean of the path-loss exponent")
    prior_n_std: float = field(0.8, "prior std of the path-loss exponent")
    n_bounds: list[float] = field([1.0, 6.0], "path-loss exponent bounds [min, max]")
    prior_pos_std_m: float = field(15.0, "std of the AP-position prior around its initial guess (m)")
    init_top_k: int = field(3, "the AP position starts at the mean of its k strongest fingerprints")
    fit_iters: int = field(40, "Gauss-Newton iterations of the AP fit")
    min_fingerprints: int = field(2, "an AP heard in fewer map scans is not used")
    min_signal_dbm: float = field(-100.0, "readings below this (dBm) are ignored")
    min_aps: int = field(3, "fewer usable APs in a scan -> no fix")
    n_starts: int = field(4, "positioning starts: the strongest APs' positions (+ their weighted centroid)")
    locate_iters: int = field(25, "Gauss-Newton iterations per start when positioning")
    clip_margin_m: float = field(10.0, "estimates are clipped to the map's bounding box grown by this (m)")
    inflate_by_residual: bool = field(True, "scale the fix covariance by the reduced chi-square when > 1")
    model_error_m: float = field(2.0, "std of the position error the model cannot see (walls, spatially "
                                      "correlated shadowing), added isotropically to the fix covariance (m)")

    def validate(self) -> None:
        n = type(self).__name__
        for name in ("sigma_db", "sigma_nu0", "d0_m", "prior_A_std_db", "prior_n_std", "prior_pos_std_m"):
            require(getattr(self, name) > 0, n, name, "> 0", getattr(self, name))
        require(len(self.n_bounds) == 2 and 0 < self.n_bounds[0] < self.n_bounds[1], n, "n_bounds",
                  "[min, max] with 0 < min < max", self.n_bounds)
        for name in ("init_top_k", "fit_iters", "min_fingerprints", "min_aps", "n_starts", "locate_iters"):
            require(int(getattr(self, name)) >= 1, n, name, "an integer >= 1", getattr(self, name))
        require(self.min_aps >= 2, n, "min_aps", ">= 2 (two unknowns)", self.min_aps)
        require(self.clip_margin_m >= 0, n, "clip_margin_m", ">= 0", self.clip_margin_m)
        require(self.model_error_m >= 0, n, "model_error_m", ">= 0", self.model_error_m)


def model(theta: np.ndarray, r: np.ndarray, d0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Path-loss model and Jacobians, broadcasting theta (..., 4) = [A, n, px, py] against r (..., 2).

    Returns (h (...,) dBm, dh/dtheta (..., 4), dh/dr (..., 2)).
    """
    diff = r - theta[..., 2:4]
    d2 = np.einsum("...i,...i->...", diff, diff) + d0 * d0
    log10d = 0.5 * np.log10(d2)
    n = theta[..., 1]
    h = theta[..., 0] - 10.0 * n * log10d
    dr = (-10.0 / LN10) * (n / d2)[..., None] * diff
    J = np.empty(h.shape + (4,))
    J[..., 0] = 1.0
    J[..., 1] = -10.0 * log10d
    J[..., 2:4] = -dr
    return h, J, dr


class PathLoss(Positioner):
    """Per-AP log-distance path-loss models (Gauss–Newton fit) and Gauss–Newton positioning."""
    name = "pathloss"

    def __init__(self, params: PathLossParams | None = None) -> None:
        self.params = params or PathLossParams()
        self.params.validate()
        self.aps = ApIndex()
        self.theta = np.zeros((0, 4))
        self.theta_cov = np.zeros((0, 4, 4))
        self.sigma2 = np.zeros(0)
        self.n_obs = np.zeros(0, np.int64)
        self.bbox = np.array([[-np.inf, -np.inf], [np.inf, np.inf]])

    # ------------------------------------------------------------------------------------------
    @property
    def bssids(self) -> list[str]:
        """The APs (column order) this method knows."""
        return self.aps.bssids

    def fit(self, radio_map: RadioMap) -> "PathLoss":
        """Fit every AP's [A, n, px, py] and its covariance from the radio map (vectorised)."""
        p = self.params
        pos = np.asarray(radio_map.positions, float)
        rss = np.asarray(radio_map.rssi_dbm, float)
        if pos.ndim != 2 or pos.shape[1] != 2 or rss.shape != (len(pos), len(radio_map.bssids)) or len(pos) == 0:
            raise MapError(f"pathloss: radio map expected positions (M, 2), M > 0, and rssi (M, A), got "
                           f"{pos.shape}, {rss.shape}")
        self.aps = ApIndex(radio_map.bssids)
        self.bbox = np.array([pos.min(0) - p.clip_margin_m, pos.max(0) + p.clip_margin_m])
        Z = rss.T  # (A, M)
        mask = np.isfinite(Z) & (np.nan_to_num(Z, nan=-999.0) >= p.min_signal_dbm)
        A, M = Z.shape
        self.n_obs = mask.sum(axis=1)
        # observed (AP, fingerprint) pairs only: the cost is proportional to the readings, not A * M
        ai, mi = np.nonzero(mask)
        zo, po = Z[ai, mi], pos[mi]
        # initial AP position: mean of its k strongest fingerprints
        k = min(p.init_top_k, M)
        order = np.argsort(np.where(mask, -Z, np.inf), axis=1)[:, :k]  # strongest first
        top_ok = np.take_along_axis(mask, order, axis=1)
        cnt = np.maximum(top_ok.sum(1), 1)
        p0 = np.einsum("ak,aki->ai", top_ok.astype(float), pos[order]) / cnt[:, None]
        theta = np.zeros((A, 4))
        theta[:, 1] = p.prior_n
        theta[:, 2:4] = p0
        _, J0, _ = model(theta[ai], po, p.d0_m)
        # least-squares A given n and position, shrunk to the prior
        wA = 1.0 / p.sigma_db ** 2
        num = wA * np.bincount(ai, zo - J0[:, 1] * p.prior_n, A) + p.prior_A_dbm / p.prior_A_std_db ** 2
        theta[:, 0] = num / (wA * self.n_obs + 1.0 / p.prior_A_std_db ** 2)
        prior_mean = np.c_[np.full(A, p.prior_A_dbm), np.full(A, p.prior_n), p0]
        prior_info = np.diag([p.prior_A_std_db ** -2, p.prior_n_std ** -2, p.prior_pos_std_m ** -2,
                              p.prior_pos_std_m ** -2])
        sig2 = np.full(A, p.sigma_db ** 2)

        # np.nonzero is row-major, so each AP's readings are one contiguous run of the arrays; APs
        # that have converged are frozen and their readings dropped from later iterations. A selection of
        # readings is (their indices, their APs, which APs have any, where each AP's run starts)
        Sel = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]

        def select(idx: np.ndarray) -> Sel:
            a_s = ai[idx]
            counts = np.bincount(a_s, minlength=A)
            has = counts > 0
            return idx, a_s, has, np.r_[0, np.cumsum(counts)[:-1]][has]

        def per_ap(v: np.ndarray, sel: Sel) -> np.ndarray:
            """Sum rows of v (n_sel, ...) — the readings of ``sel`` — per AP -> (A, ...)."""
            _, _, has, starts = sel
            out = np.zeros((A,) + v.shape[1:])
            if has.any():
                out[has] = np.add.reduceat(v, starts, axis=0)
            return out

        def cost(th: np.ndarray, sel: Sel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            idx, a_s = sel[0], sel[1]
            h, J, _ = model(th[a_s], po[idx], p.d0_m)
            res = zo[idx] - h
            dp = th - prior_mean
            c = per_ap(res ** 2, sel) / sig2 + np.einsum("ai,ij,aj->a", dp, prior_info, dp)
            return c, res, J

        iu, ju = np.triu_indices(4)

        def normal_eq(res: np.ndarray, J: np.ndarray, th: np.ndarray, sel: Sel) -> tuple[np.ndarray, np.ndarray]:
            upper = per_ap(J[:, iu] * J[:, ju], sel)              # the 10 distinct products of J^T J per AP
            H = np.empty((A, 4, 4))
            H[:, iu, ju] = upper
            H[:, ju, iu] = upper
            H = H / sig2[:, None, None] + prior_info
            g = per_ap(J * res[:, None], sel) / sig2[:, None] - (th - prior_mean) @ prior_info
            return H, g

        everything = select(np.arange(len(ai)))
        lam = np.full(A, 1e-3)
        c, res, J = cost(theta, everything)
        active = np.ones(A, bool)
        eye4 = np.eye(4)
        sel = everything
        for _ in range(p.fit_iters):
            idx = sel[0]
            H, g = normal_eq(res[idx], J[idx], theta, sel)
            Hd = H + lam[:, None, None] * (np.einsum("aii->ai", H)[:, :, None] * eye4)
            cand = theta.copy()
            cand[active] += np.linalg.solve(Hd[active], g[active][..., None])[..., 0]
            cand[:, 1] = np.clip(cand[:, 1], p.n_bounds[0], p.n_bounds[1])
            cand[~active] = theta[~active]
            c2, res2, J2 = cost(cand, sel)
            better = (c2 < c) & active
            moved = np.abs(cand - theta).max(axis=1)
            theta = np.where(better[:, None], cand, theta)
            c = np.where(better, c2, c)
            keep = better[sel[1]]
            res[idx] = np.where(keep, res2, res[idx])
            J[idx] = np.where(keep[:, None], J2, J[idx])
            lam = np.clip(np.where(better, lam * 0.1, lam * 10.0), 1e-9, 1e9)
            still = active & (moved >= 1e-3)  # mdB and mm (after the bounds): the others have converged
            if (still != active).any():
                active = still
                if not active.any():
                    break
                sel = select(idx[active[sel[1]]])
        # per-AP noise variance (shrinkage to sigma0) and parameter covariance
        dof = np.maximum(self.n_obs - 4, 0) + p.sigma_nu0
        sig2 = (per_ap(res ** 2, everything) + p.sigma_nu0 * p.sigma_db ** 2) / dof
        H, _ = normal_eq(res, J, theta, everything)
        self.theta = theta
        self.theta_cov = np.linalg.inv(H)
        self.sigma2 = sig2
        return self

    @property
    def usable(self) -> np.ndarray:
        """(A,) APs with enough fingerprints to be used in positioning."""
        return self.n_obs >= self.params.min_fingerprints

    # ------------------------------------------------------------------------------------------
    def locate(self, scan: WifiScan) -> Fix:
        """Multi-start Gauss–Newton position of one scan with an honest covariance."""
        p = self.params
        nan2, big = np.full(2, np.nan), np.full((2, 2), np.nan)
        if len(scan) == 0:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="empty_scan")
        if not self.bssids:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="no_map")
        r = np.asarray(scan.rssi_dbm, float)
        idx = self.aps.columns(scan.bssid)
        keep = (idx >= 0) & np.isfinite(r) & (r >= p.min_signal_dbm)
        keep[keep] &= self.usable[idx[keep]]
        idx, z = idx[keep], r[keep]
        if len(idx) == 0:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="no_known_ap")
        if len(idx) < p.min_aps:
            return Fix(scan.stamp_ns, nan2, big, ok=False, reason="too_few_aps", info={"n_aps": int(len(idx))})
        th, C, s2 = self.theta[idx], self.theta_cov[idx], self.sigma2[idx]
        # starts: positions of the strongest APs and their power-weighted centroid
        order = np.argsort(-z)
        starts = [th[order[:max(p.n_starts - 1, 1)], 2:4]]
        wpow = 10.0 ** ((z - z.max()) / 10.0)
        starts.append((wpow @ th[:, 2:4] / wpow.sum())[None])
        x = np.clip(np.vstack(starts), self.bbox[0], self.bbox[1])  # (S, 2)
        # tiny offset so a start at an AP position still has a gradient for that AP
        x = x + np.array([0.05, 0.05])

        def evaluate(xs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            h, Jt, Jr = model(th[None], xs[:, None, :], p.d0_m)  # (S, K), (S, K, 4), (S, K, 2)
            var = s2 + np.einsum("ski,kij,skj->sk", Jt, C, Jt)
            res = z - h
            return (res ** 2 / var).sum(1), res, Jr, var

        c, res, Jr, var = evaluate(x)
        lam = np.full(len(x), 1e-3)
        for _ in range(p.locate_iters):
            Jw = Jr / var[..., None]
            H = np.einsum("ski,skj->sij", Jw, Jr)
            g = np.einsum("ski,sk->si", Jw, res)
            Hd = H + lam[:, None, None] * (np.einsum("sii->si", H)[:, :, None] * np.eye(2)) + 1e-9 * np.eye(2)
            cand = np.clip(x + np.linalg.solve(Hd, g[..., None])[..., 0], self.bbox[0], self.bbox[1])
            c2, res2, Jr2, var2 = evaluate(cand)
            better = c2 < c
            x = np.where(better[:, None], cand, x)
            c = np.where(better, c2, c)
            res = np.where(better[:, None], res2, res)
            Jr = np.where(better[:, None, None], Jr2, Jr)
            var = np.where(better[:, None], var2, var)
            lam = np.clip(np.where(better, lam * 0.1, lam * 10.0), 1e-9, 1e9)
        b = int(np.argmin(c))
        H = (Jr[b] / var[b][:, None]).T @ Jr[b]
        cov = np.linalg.inv(H + 1e-9 * np.eye(2))
        K = len(idx)
        chi2_red = float(c[b]) / max(K - 2, 1)
        if p.inflate_by_residual and chi2_red > 1.0:
            cov = cov * chi2_red
        cov = 0.5 * (cov + cov.T) + p.model_error_m ** 2 * np.eye(2)
        return Fix(scan.stamp_ns, x[b].copy(), cov,
                   info={"n_aps": K, "cost": float(c[b]), "chi2_red": chi2_red, "start": b})
