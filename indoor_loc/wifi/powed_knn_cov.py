"""The covariance of a powed k-NN fix, calibrated on the radio map itself (:class:`CovarianceCalibration`,
mixed into :class:`indoor_loc.wifi.powed_knn.PowedKnn`), and the per-fix quantities that may rank its error.

Covariance: ``cov_scale`` × the weighted spread of the k neighbours + σ² I, σ calibrated on the map itself
at ``fit`` time by leaving walks out: the map's sources (walks) are dealt into at most ``cov_folds`` folds
and each map scan is positioned against the map without its fold's walks (the grid interpolated again
without them). σ follows a *score* of each fix: with ``cov_quantities`` 'd1' (the default) the distance D₁
of the best match (a poor best match means a scan the map does not explain, and its error tends to be
larger); with several quantities the least-squares prediction of the log cross-validated error from them,
fitted on the cross-validated scans of this map. The (score, error) pairs are sorted by the score into
equal-count bins (at most ``cov_bins``, at least 40 scans each), and in each bin σ is set so that the
``cov_quantile`` ellipse of an isotropic 2-D Gaussian holds that share of the bin's cross-validated errors:
σ = q-quantile(error) / sqrt(−2 ln(1 − q)); σ is made non-decreasing in the score and interpolated between
bin centres (constant beyond the end ones).
Every fix carries the quantities that might rank its error in ``info["features"]``: D₁ and D₁ against the
k-th match (``d_ratio``), the largest distance between the estimates it averages (``views_m``: ages weighted
or ignored, against the map scans or the grid — hypotheses that disagree mean an ambiguous scan), the
weight of its candidates beyond 5 m of it (``far``, a second mode), the weighted spread of each view's
candidates (``spread_m``), the distance between the map scans' and the grid's estimates (``view_gap_m``),
the grid's share on the survey (``survey_share``) and the APs matched (``n_aps``); the calibration keeps
their rank correlation (Spearman) with the cross-validated errors (``calibration["spearman"]``). On
ms_site2 none of them ranks the errors better than D₁ on every floor, and which one does best differs
between the map's cross-validation and the test walks: on the test walks D₁ gives B1 0.19, F3 0.56, F7
0.74, F8 0.37, while ``views_m`` gives B1 0.22 and F8 0.39 but F3 0.10, D₁ against the k-th match F3 0.62,
the spread F8 0.56 (cross-validated on F8's map: −0.29 for ``views_m``, 0.16 for the spread). A σ on D₁ and
``views_m`` (fitted per building) with the strata as factors (below), chosen on B1 and F7 with a third of
their survey walks left out in turn, ranked the errors better there (Spearman of σ with the error B1 0.11 →
0.25, F7 0.70 → 0.73) and on held-out F3 (0.34 → 0.42; F8 0.32 → 0.26), but F3's ellipses then held 37/68 %
of its test truths (50/95 %) instead of 61/85 (F8 58/88 instead of 56/87) — so it is an option, not the
default.
Positioning errors are heavy-tailed (a scan matched to the wrong part of a
mall is tens of metres off), so a σ fitted to the mean error — or a line in D₁ — leaves the 95 %
ellipse far too small where the errors are large; calibrating the 95 % ellipse keeps the
covariance honest where a downstream filter gates on it, at the price of a 50 % ellipse that holds
more than half of the truths. The calibration follows each building's own accuracy instead of
constants fitted to one building; a map with a single source (a pre-surveyed map) deals its scans
into the folds instead (without a grid: leaves one scan out). Cross-validation cannot see what the
survey never covered: a user walking where no survey walk went is positioned on the nearest
surveyed stretch and its error exceeds the ellipse (on ms_site2 F3 most test scans are more than
3 m from every map scan).

**Recording time** (``cov_recent_s``): RSS drifts over minutes to days — people, doors, AP power control
(Kaemarungsi & Krishnamurthy, "Properties of indoor received signal strength for WLAN location
fingerprinting", MobiQuitous 2004; Mendoza-Silva et al., "Long-term WiFi fingerprinting dataset for
research on robust indoor positioning", Data 3(1), 2018) — so a scan matched to map scans recorded minutes
before it shares their transient state: it matches them better (a smaller D₁) than a scan from another
session at the same distance from the survey, and D₁ alone says less about its error. The calibration
therefore treats apart the cross-validated scans whose nearest matched map scan (in recording time) is
within ``cov_recent_s`` of them and the rest, and a fix is calibrated by its own stratum (a stratum with
fewer than 40 scans, or a map without recording times, uses all scans). With ``cov_strata`` 'tables' (the
default) each stratum has its own table; with 'factor' σ is the one table over all scans times one factor
per stratum, the factor whose ellipse holds that stratum's share of its scans' errors divided by the
table's σ. Per-stratum tables are fitted on a few dozen scans a bin and their levels can swap between
strata: on ms_site2 F7 with a third of the survey walks left out in turn, the tables' σ ranked the left-out
walks' errors at −0.40, 0.52 and 0.54 (Spearman, per third) where one table ranks them at 0.60, 0.74 and
0.51, and one table with factors at 0.51, 0.75, 0.77 (B1: 0.13, 0.19, 0.00; 0.43, 0.40, 0.04; 0.32, 0.34,
0.03). A user positioned days after the survey gets the second stratum; a replay of the survey session's
other walks mostly the first. The positions do not depend on the covariance.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from indoor_loc.wifi.powed_knn_params import COV_QUANTITIES, MIN_BIN_SCANS, PowedKnnParams, cov_quantity_names
from indoor_loc.wifi.powed_repr import sorensen
from indoor_loc.wifi.types import RadioMap

if TYPE_CHECKING:
    from indoor_loc.wifi.powed_knn import _View


def cov_columns(names: list[str], q: dict[str, Any]) -> np.ndarray:
    """(N, len(names)) the quantities ``q`` (name -> value or (N,) values) on the scale the calibration's
    least-squares fit uses: distances in metres and AP counts by their logarithm (log(1 + m), log n), the rest as
    they are (the best-match distance, shares and ratios in [0, 1]). ValueError when ``q`` lacks one of ``names``
    (the score of a fix without it would be wrong, not merely less informed)."""
    missing = [name for name in names if name not in q]
    if missing:
        raise ValueError(f"expected the per-fix quantities {names} (a fix's info['features']), got no {missing}")
    cols = []
    for name in names:
        v = np.atleast_1d(np.asarray(q[name], float))
        cols.append(np.log1p(np.maximum(v, 0.0)) if name.endswith("_m") else
                    np.log(np.maximum(v, 1.0)) if name == "n_aps" else v)
    return np.column_stack(cols)


#: radius (m) around a fix beyond which its candidates' weight counts as a second hypothesis
FAR_M = 5.0


def fix_features(xy: np.ndarray, pos: np.ndarray, parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, Any]],
              survey_share: float) -> dict[str, float]:
    """Per-fix quantities that may say how far off a fix is: the best-match distance ``d1`` and its ratio to the
    first view's k-th, the weighted spread (m) of each view's candidates about the view's own estimate,
    averaged over views (``spread_m``), the distance between the estimates against the map scans and against
    the grid (``view_gap_m``, 0 without a grid), the largest distance between two views' estimates
    (``views_m``), the weight of the candidates farther than :data:`FAR_M` from the fix (``far``), and the
    grid's share on the survey (``survey_share``, 1 without the field)."""
    est, spread, far = [], [], 0.0
    for rows, x, _, _ in parts:
        p = pos[rows]
        e = x @ p
        est.append(e)
        spread.append(math.sqrt(float(x @ np.sum((p - e) ** 2, axis=1))))
        far += float(x @ (np.hypot(*(p - xy).T) > FAR_M)) / len(parts)
    grid = [e for e, (_, _, _, v) in zip(est, parts) if v.grid]
    scans = [e for e, (_, _, _, v) in zip(est, parts) if not v.grid]
    gap = float(np.hypot(*(np.mean(grid, axis=0) - np.mean(scans, axis=0)))) if grid and scans else 0.0
    e_all = np.array(est)
    views = float(np.max(np.hypot(*(e_all[:, None] - e_all[None]).reshape(-1, 2).T)))
    d = parts[0][2]
    return {"d1": float(d[0]), "d_ratio": float(d[0] / max(float(d[-1]), 1e-12)), "spread_m": float(np.mean(spread)),
            "view_gap_m": gap, "views_m": views, "far": far, "survey_share": survey_share}


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman's rank correlation of x and y over the pairs where both are finite (NaN with fewer than 3)."""
    from scipy.stats import spearmanr
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(x[ok]) == 0 or np.ptp(y[ok]) == 0:
        return float("nan")
    return float(spearmanr(x[ok], y[ok]).statistic)


class CovarianceCalibration:
    """Leave-walks-out calibration of a fix's sigma (``fit``) and the sigma of a fix (``sigma_m``)."""

    if TYPE_CHECKING:     # provided by PowedKnn
        params: PowedKnnParams
        radio_map: RadioMap | None
        _n_map: int
        _pos: np.ndarray
        _z: np.ndarray
        _kernel: Any
        _kernel_sums: list[Any] | None
        _vals: list[np.ndarray]
        _views: list[_View]
        _last_features: dict[str, float]
        _cv_features: dict[str, np.ndarray]
        sigma_table: tuple[np.ndarray, np.ndarray]
        sigma_tables: tuple[tuple[np.ndarray, np.ndarray], ...]
        sigma_factors: tuple[float, ...]
        cov_coef: np.ndarray
        calibration: dict[str, Any]

        def _off_survey(self, keep: np.ndarray) -> np.ndarray | None: ...
        def _smoothed(self, keep: np.ndarray, floor: float | None = None
                      ) -> tuple[list[Any], list[Any], np.ndarray]: ...
        def _estimate(self, ds: list[np.ndarray], allowed: np.ndarray, pos: np.ndarray | None = None,
                      views: list[_View] | None = None, off: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray] | None: ...

    def _calibrate(self, source: list[str], map_z: np.ndarray) -> None:
        """Leave-one-source-out errors of the map's own scans -> sigma per bin of the best-match distance.
        With smoothing the grid is interpolated again without the left-out source's scans."""
        from scipy import sparse
        p = self.params
        m = self._n_map
        # leave walks (sources) out: the sources, in name order, are dealt into at most cov_folds folds;
        # a map from one source (a survey) deals its scans instead. Without a grid and with few sources
        # that is leave-one-source-out; a grid is interpolated again for every fold.
        names = sorted(set(source))
        if len(names) >= 2:
            rank = {name: i for i, name in enumerate(names)}
            src = np.array([rank[s] % int(p.cov_folds) for s in source])
        elif self._kernel is None:
            src = np.arange(m)
        else:
            src = np.arange(m) % min(m, int(p.cov_folds))
        d1 = np.full(m, np.nan)
        err = np.full(m, np.nan)
        lag = np.full(m, np.inf)                  # s from each scan to its nearest matched map scan (recording time)
        feats: dict[str, np.ndarray] = {}
        assert self.radio_map is not None
        stamps = np.asarray(self.radio_map.stamps_ns, np.int64)
        rows = np.unique(np.linspace(0, m - 1, min(m, int(p.cov_calibration_scans))).round().astype(int))
        views = [v for v in self._views if not v.twin]           # the map scans have no ages to ignore
        if self._kernel is not None:                 # every fold starts from the kernel sums over all scans
            self._kernel_sums = [sparse.csr_matrix(self._kernel @ sparse.csr_matrix(v)) for v in self._vals]
        floors = np.unique(map_z)
        for fold in np.unique(src[rows]):
            keep = src != fold
            off = self._off_survey(keep)
            # candidates: the map scans, then every grid point (a floor's points out of reach of the kept scans
            # are in no floor's part: their distance stays 1, no candidate)
            n_c = len(self._pos)
            pos_c, z_c = self._pos, self._z
            allowed = np.concatenate([keep, np.ones(n_c - m, bool)])
            for zf in floors:
                # a scan is matched on its own floor only: the distances to the other floors' grid points
                # are never read (they stay 1, no candidate)
                on_floor = allowed & (z_c == zf)
                todo = rows[(src[rows] == fold) & (map_z[rows] == zf)]
                if len(todo) == 0:
                    continue
                if self._kernel is not None:             # this floor's grid without the fold's scans
                    g_rd: list[Any] = []                 # (the previous floor's freed first)
                    g_sums: list[Any] = []
                    g_rd, g_sums, part = self._smoothed(keep, float(zf))
                for i in todo:
                    c = np.flatnonzero(self._vals[0][i] > 0)
                    if len(c) == 0:
                        continue
                    ds = []
                    for v in views:
                        d = np.ones(n_c)
                        if v.grid:
                            d[m + part] = sorensen(c, self._vals[v.values][i, c], g_rd[v.values],
                                                    g_sums[v.values], len(part))
                        else:
                            rd, sm, _ = v.parts[0]
                            d[:m] = sorensen(c, self._vals[v.values][i, c], rd, sm, m)
                        ds.append(d)
                    est = self._estimate(ds, on_floor, pos_c, views, off)
                    if est is None:
                        continue
                    d1[i] = est[3]
                    err[i] = float(np.hypot(*(est[0] - self._pos[i])))
                    lag[i] = self._lag_s(est[1], int(stamps[i]))
                    for key, val in self._last_features.items():
                        feats.setdefault(key, np.full(m, np.nan))[i] = val
                    feats.setdefault("n_aps", np.full(m, np.nan))[i] = len(c)
        self._kernel_sums = None
        ok = np.isfinite(err)
        if ok.sum() < 10:
            return
        d1, err, lag = d1[ok], err[ok], lag[ok]
        self._cv_features = {key: val[ok] for key, val in feats.items()} | {"error_m": err, "lag_s": lag}
        names = cov_quantity_names(p.cov_quantities)
        if names != ["d1"]:
            # the score: the least-squares prediction of the log error from the quantities (scans with all of them)
            a = np.column_stack([np.ones(len(err)), cov_columns(names, self._cv_features)])
            good = np.all(np.isfinite(a), axis=1)
            if good.sum() >= 10:
                self.cov_coef = np.linalg.lstsq(a[good], np.log(np.maximum(err[good], p.cov_floor_m)), rcond=None)[0]
        score = self.cov_score(self._cv_features) if len(self.cov_coef) else d1
        self.sigma_table = self._sigma_bins(score, err)
        self.calibration = {"scans": int(len(err)), "mean_error_m": float(np.mean(err)),
                            "quantile": p.cov_quantile, "quantities": names if len(self.cov_coef) else ["d1"],
                            "coef": self.cov_coef.tolist(), "score": self.sigma_table[0].tolist(),
                            "sigma_m": self.sigma_table[1].tolist(),
                            "spearman": {key: spearman(val, err) for key, val in self._cv_features.items()
                                         if key in COV_QUANTITIES}}
        recent = lag <= p.cov_recent_s
        if p.cov_recent_s > 0 and np.ptp(stamps) > 0:     # a map with recording times (not a pre-surveyed one)
            strata = (recent, ~recent)
            if p.cov_strata == "tables":
                self.sigma_tables = tuple(self._sigma_bins(score[s], err[s]) if s.sum() >= MIN_BIN_SCANS
                                          else self.sigma_table for s in strata)
                self.calibration.update(recent_sigma_m=self.sigma_tables[0][1].tolist(),
                                        recent_score=self.sigma_tables[0][0].tolist(),
                                        older_sigma_m=self.sigma_tables[1][1].tolist(),
                                        older_score=self.sigma_tables[1][0].tolist())
            else:
                # one shape over all scans; per stratum, the factor whose ellipse holds its share of the stratum's
                # errors (a stratum under MIN_BIN_SCANS keeps the shape)
                shape = np.maximum(np.interp(score, *self.sigma_table), p.cov_floor_m)
                scale = math.sqrt(-2.0 * math.log(1.0 - p.cov_quantile))
                self.sigma_factors = tuple(float(np.quantile(err[s] / shape[s], p.cov_quantile)) / scale
                                           if s.sum() >= MIN_BIN_SCANS else 1.0 for s in strata)
                self.calibration.update(factors=list(self.sigma_factors))
            self.calibration.update(recent_scans=int(recent.sum()), recent_mean_error_m=float(np.mean(err[recent]))
                                    if recent.any() else float("nan"))

    def _sigma_bins(self, d1: np.ndarray, err: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cross-validated (score, error) -> (bin centres, sigma per bin): equal-count bins of the score (the
        best-match distance or the predicted log error; at most ``cov_bins``, at least 40 scans each), per bin
        the sigma whose ``cov_quantile`` ellipse holds that share of the bin's errors, made non-decreasing in
        the score."""
        p = self.params
        order = np.argsort(d1, kind="stable")
        bins = np.array_split(order, int(np.clip(len(order) // MIN_BIN_SCANS, 1, int(p.cov_bins))))
        centres = np.array([float(np.mean(d1[b])) for b in bins])
        scale = math.sqrt(-2.0 * math.log(1.0 - p.cov_quantile))
        sig = np.maximum.accumulate(np.array([float(np.quantile(err[b], p.cov_quantile)) / scale for b in bins]))
        return centres, np.maximum(sig, p.cov_floor_m)

    def _lag_s(self, rows: np.ndarray, stamp_ns: int) -> float:
        """Time (s) between a scan and the nearest in recording time of the map scans among the fix's
        candidate ``rows`` (inf when the fix has none, e.g. grid points only)."""
        assert self.radio_map is not None
        r = rows[rows < self._n_map]
        if len(r) == 0:
            return math.inf
        return float(np.min(np.abs(np.asarray(self.radio_map.stamps_ns, np.int64)[r] - int(stamp_ns)))) / 1e9

    def cov_score(self, q: dict[str, Any]) -> np.ndarray:
        """The calibration's score of fixes with quantities ``q`` (name -> value or (N,) values; fix
        ``info["features"]``): the predicted log error, or the best-match distance when sigma is calibrated on it
        alone."""
        if not len(self.cov_coef):
            return np.atleast_1d(np.asarray(q["d1"], float))
        names = self.calibration.get("quantities") or cov_quantity_names(self.params.cov_quantities)
        return self.cov_coef[0] + cov_columns(names, q) @ self.cov_coef[1:]

    def sigma_m(self, d1: float, lag_s: float | None = None, features: dict[str, float] | None = None) -> float:
        """Isotropic standard deviation of a fix whose best match is at distance ``d1``, m, with the other
        quantities of the calibration's score in ``features`` (fix ``info["features"]``; needed, ValueError without
        them, when ``cov_quantities`` names more than 'd1'); with ``lag_s`` (s from the scan to its nearest matched
        map scan) that of its recording-time stratum."""
        x = float(self.cov_score({**(features or {}), "d1": d1})[0]) if len(self.cov_coef) else d1
        centres, sig = self.sigma_table
        stratum = None if lag_s is None else 0 if lag_s <= self.params.cov_recent_s else 1
        if stratum is not None and self.sigma_tables:
            centres, sig = self.sigma_tables[stratum]
        s = max(self.params.cov_floor_m, float(np.interp(x, centres, sig)))
        if stratum is not None and self.sigma_factors:
            s *= self.sigma_factors[stratum]
        return max(self.params.cov_floor_m, s)
